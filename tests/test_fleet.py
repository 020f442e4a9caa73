"""A fleet calibrated in one command: each robot in its folder, a broken one reported, the others finish."""
from pathlib import Path

import pytest

from pipeline.commands import fleet
from pipeline.lib.project.config import load_params

ROOT = Path(__file__).resolve().parents[1]


def test_robot_params_merge_the_override_over_the_project(tmp_path):
    d = tmp_path / "r1"
    d.mkdir()
    (d / "params.yaml").write_text("robot: {model: ur10}\ningest: {joints: j.csv, tracker: t.csv}\n")
    (d / "j.csv").write_text("joints")
    p = fleet.robot_params(load_params(ROOT / "params.yaml"), d)
    assert p["robot"]["model"] == "ur10" and p["ingest"]["joints"] == "campaign/j.csv"   # the copy's, relative
    assert p["validate"]["campaigns"] == {} and p["campaigns"]["more"] == {}
    assert p["model"] == load_params(ROOT / "params.yaml")["model"]          # the rest: the project's
    job = fleet.robot_job(load_params(ROOT / "params.yaml"), d, 1)            # the folder travels as bytes
    assert job["robot"] == "r1" and job["params"] == p and job["threads"] == 1
    assert job["files"] == {"j.csv": b"joints", "params.yaml": (d / "params.yaml").read_bytes()}


def test_empty_fleet_folder_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="no robot folders"):
        fleet.run_fleet(tmp_path / "none")


# The fleet on Ray, a broken campaign reported and the other robot calibrated: tests/test_sweep.py
# (test_sweep_and_fleet_on_a_two_node_cluster).

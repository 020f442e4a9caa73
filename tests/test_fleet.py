"""A fleet calibrated in one command: each robot in its folder, a broken one reported, the others finish."""
import json
from pathlib import Path

import pytest

from pipeline import fleet
from pipeline.lib.config import load_params

ROOT = Path(__file__).resolve().parents[1]


def small(params: dict) -> dict:
    params["model"].update(d_model=12, n_head=2, n_layer=1, d_hidden=32)
    params["train"].update(max_epochs=6, patience=6)
    return params


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


@pytest.mark.slow
@pytest.mark.xdist_group("serial")   # one Ray at a time (a second ray.init could join the first)
def test_fleet_on_ray_reports_a_broken_campaign_and_finishes_the_others(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    robots = fleet.demo("fleet_in", robots=3, n=150)                     # ur5_01, ur10_02, ur5_03
    assert [r.name for r in robots] == ["ur5_01", "ur10_02", "ur5_03"]
    broken = robots[2] / "tracker.csv"
    broken.write_text(broken.read_text().replace("X,Y,Z", "X,Y,Q", 1))    # a column the reader needs
    s = fleet.run_fleet("fleet_in", "out", engine="ray", base=small(load_params(ROOT / "params.yaml")))
    assert s["n_robots"] == 3 and s["n_ok"] == 2
    assert list(s["failed"]) == ["ur5_03"]
    reason = s["failed"]["ur5_03"]
    assert reason.startswith("ingest:") and "campaign/tracker.csv" in reason and "column(s) z" in reason
    assert "column(s) z" in (Path("out") / "ur5_03/logs/ingest.log").read_text()    # its folder came back too
    assert {r["robot"]: r.get("model") for r in s["robots"] if r["status"] == "ok"} == \
        {"ur5_01": "ur5", "ur10_02": "ur10"}
    for r in s["robots"]:
        if r["status"] == "ok":
            e = r["test_3d_mae_mm"]
            assert e["calibrated"] < e["nominal"] / 3, r["robot"]          # each twin really calibrated
            assert (Path("out") / r["robot"] / "reports/index.md").exists()
            assert (Path("out") / r["robot"] / "models/calibrated.urdf").exists()
            # written here from what the task sent back: the campaign with it, the params pointing at it
            assert (Path("out") / r["robot"] / "campaign/tracker.csv").exists()
            assert "joints: campaign/joints.csv" in (Path("out") / r["robot"] / "params.yaml").read_text()
    assert json.loads(Path("reports/fleet.json").read_text())["n_ok"] == 2
    assert "failed in ingest" in Path("reports/fleet.md").read_text()

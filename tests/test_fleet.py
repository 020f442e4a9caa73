"""A fleet calibrated in one command: each robot in its folder, a broken one reported, the others finish."""
import re
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
    job = fleet.robot_job(load_params(ROOT / "params.yaml"), d)               # the folder travels as bytes
    assert job["robot"] == "r1" and job["params"] == p
    assert job["files"] == {"j.csv": b"joints", "params.yaml": (d / "params.yaml").read_bytes()}


def test_empty_fleet_folder_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="no robot folders"):
        fleet.run_fleet(tmp_path / "none")


# The fleet on Ray, a broken campaign reported and the other robot calibrated: tests/test_sweep.py
# (test_sweep_and_fleet_on_a_two_node_cluster).


@pytest.mark.parametrize("override, words", [
    ("ingest: {joints: /etc/passwd, tracker: t.csv}\n", "ingest.joints: '/etc/passwd' is not a path inside the robot's folder"),
    ("ingest: {joints: ../../x.csv, tracker: t.csv}\n", "ingest.joints: '../../x.csv' is not a path inside"),
    ("- a list\n", "expected a mapping of params.yaml sections"),
    ("ingest: null\n", "expected a mapping of params.yaml sections"),
    ("robot: {model: [\n", "not YAML"),
])
def test_a_robots_bad_params_name_its_file(tmp_path, override, words):
    """Before: a campaign path could leave the robot's folder (the driver read /etc/passwd into fleet.json),
    and a params.yaml that is a list, no YAML or `ingest: null` was a traceback naming no file."""
    d = tmp_path / "r1"
    d.mkdir()
    (d / "params.yaml").write_text(override)
    with pytest.raises(ValueError, match=re.escape(str(d / "params.yaml"))) as e:
        fleet.robot_params(load_params(ROOT / "params.yaml"), d)
    assert words in str(e.value)


def test_a_robot_whose_params_are_refused_fails_alone(tmp_path, monkeypatch):
    """One robot's bad params.yaml aborted the whole fleet before any robot ran, and a hidden folder
    (.ipynb_checkpoints) counted as a robot. Now that robot is reported failed in `params`, the hidden folder
    is no robot, and the others run (here one, whose campaign is missing: failed in ingest, as before)."""
    monkeypatch.chdir(tmp_path)
    for name, text in (("a|bad", "- a list\n"), ("b", "ingest: {joints: j.csv, tracker: t.csv}\n")):
        (tmp_path / "fleet" / name).mkdir(parents=True)
        (tmp_path / "fleet" / name / "params.yaml").write_text(text)
    (tmp_path / "fleet" / ".ipynb_checkpoints").mkdir()
    base = load_params(ROOT / "params.yaml")
    f = fleet.run_fleet(tmp_path / "fleet", tmp_path / "out", "sequential", base=base)
    assert [r["robot"] for r in f["robots"]] == ["a|bad", "b"] and f["n_ok"] == 0
    assert f["failed"]["a|bad"].startswith("params: ") and "expected a mapping" in f["failed"]["a|bad"]
    assert f["failed"]["b"].startswith("ingest: ")
    table = (tmp_path / "reports/fleet.md").read_text().splitlines()
    assert table[4].startswith("| a\\|bad | failed in params: ") and table[4].count(" | ") == 5


def test_the_committed_demo_fleet_is_what_the_demo_makes(tmp_path):
    """data/fleet was written before the twin measured its probe's orientation: its tracker files had no
    QW..QZ, so `fleet run data/fleet`, as the docs show it, failed every robot at ingest (the project's
    params read the orientation). The committed fleet is the demo's output, byte for byte."""
    fleet.demo(tmp_path)
    made = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file())
    committed = sorted(p.relative_to(ROOT / "data/fleet") for p in (ROOT / "data/fleet").rglob("*") if p.is_file())
    assert made == committed and len(made) == 12
    for f in made:
        assert (tmp_path / f).read_bytes() == (ROOT / "data/fleet" / f).read_bytes(), f
    assert (ROOT / "data/fleet/ur5_01/tracker.csv").read_text().startswith("Name,X,Y,Z,QW,QX,QY,QZ\n")


def test_a_stage_in_a_robots_job_leaves_no_logger_writing_to_its_log(tmp_path, monkeypatch, capsys):
    """run_logged sends a stage's log lines and prints to that stage's log alone. A library that makes its own
    handler on the stderr of the moment (dvclive does, on import in the train stage) kept writing to the
    first robot's closed log: every later robot's messages from it were lost, a "Logging error" traceback in
    their place (a review found it). Now such handlers go with the stage; the messages reach the stage's log."""
    import logging
    from pipeline import stages

    def stage(name, argv=(), root=None):                   # a stage whose library logs as dvclive does
        lib = logging.getLogger("a_library")
        if not lib.handlers:
            lib.addHandler(logging.StreamHandler())         # sys.stderr as it is now: the stage's log
        lib.warning("from %s", root.name)
        print("printed in", root.name)
    monkeypatch.setattr(stages, "run", stage)
    for robot in ("r1", "r2"):
        (tmp_path / robot / "logs").mkdir(parents=True)
        assert fleet.run_logged("train", tmp_path / robot) is None
    for robot in ("r1", "r2"):
        log = (tmp_path / robot / "logs/train.log").read_text()
        assert f"from {robot}" in log and f"printed in {robot}" in log and "Logging error" not in log
    assert "Logging error" not in capsys.readouterr().err
    assert not logging.getLogger("a_library").handlers

"""A fleet calibrated in one command: each robot in its folder, a broken one reported, the others finish."""
import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from pipeline.commands import fleet
from pipeline.lib.learning import sweep
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
    ("trian: {max_epochs: 3}\n", "unknown section(s) ['trian']"),
    ("validate: {campaigns: {b: {ingest: {joints: /etc/passwd}, frame: refit, commanded: null}}}\n",
     "validate.campaigns: {'b': "),
    ("campaigns: {name: a, station: s, more: {b: {ingest: {joints: j2.csv, tracker: t2.csv}, station: s}}}\n",
     "campaigns.more: {'b': "),
    ("compensate: {drive_check: true}\n", "compensate.drive_check: True: the fleet does not run it"),
    ("train: {lr: fast}\n", "train.lr: a learning rate > 0, got 'fast'"),
    ("ingest: {joints: j.csv, tracker: t.csv, sepp: ','}\n", "ingest: unknown key(s) ['sepp']"),
])
def test_a_robots_bad_params_name_its_file(tmp_path, override, words):
    """Before: a campaign path could leave the robot's folder (the driver read /etc/passwd into fleet.json),
    and a params.yaml that is a list, no YAML or `ingest: null` was a traceback naming no file. A misspelt
    section (`trian:`) was merged and ignored; validation campaigns, further campaigns and the drive check,
    which the fleet never runs, were dropped without a word (their paths never checked); a wrong key or value
    failed late, in its stage. Now each names the robot's params.yaml and the key before any stage runs."""
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


def test_what_the_fleet_runs_not_is_accepted_when_empty_or_off(tmp_path):
    """The settings the fleet does not run are refused only when given (a robot may say them off)."""
    d = tmp_path / "r1"
    d.mkdir()
    (d / "params.yaml").write_text("ingest: {joints: j.csv, tracker: t.csv}\nvalidate: {campaigns: {}}\n"
                                   "compensate: {drive_check: false}\n")
    p = fleet.robot_params(load_params(ROOT / "params.yaml"), d)
    assert p["validate"]["campaigns"] == {} and p["compensate"]["drive_check"] is False


def a_fleet(tmp_path, monkeypatch, robots=("b",)) -> Path:
    """tmp_path as the project (its params.yaml the project's) with a fleet of robots whose campaigns are
    missing (each fails in ingest, at once): the fleet folder."""
    monkeypatch.chdir(tmp_path)
    shutil.copy(ROOT / "params.yaml", tmp_path / "params.yaml")
    for name in robots:
        (tmp_path / "fleet" / name).mkdir(parents=True)
        (tmp_path / "fleet" / name / "params.yaml").write_text("ingest: {joints: j.csv, tracker: t.csv}\n")
    return tmp_path / "fleet"


def test_a_job_that_fails_outside_its_stages_is_its_robots_row(tmp_path, monkeypatch):
    """A robot's job that raised outside its stages (a robot folder's name too long for its scratch folder's
    prefix: OSError; torch refusing --threads -1) made sweep.run raise SweepFailed: a traceback, and
    reports/fleet.json and fleet.md stayed those of the previous fleet. Now it is that robot's failed row
    (step `job`, the error), the others' rows stand and the reports are written."""
    root = a_fleet(tmp_path, monkeypatch, ("a", "b"))
    (tmp_path / "reports").mkdir()
    (tmp_path / "reports/fleet.json").write_text('{"previous": "fleet"}')
    real = fleet.calibrate_robot

    def calibrate(job):
        if job["robot"] == "a":
            raise OSError("[Errno 36] File name too long: '/tmp/fleet-aaaa'")
        return real(job)
    monkeypatch.setattr(fleet, "calibrate_robot", calibrate)
    f = fleet.run_fleet(root, tmp_path / "out", "sequential", base=load_params())
    assert f["failed"]["a"] == "job: OSError: [Errno 36] File name too long: '/tmp/fleet-aaaa'"
    assert f["failed"]["b"].startswith("ingest: ") and (tmp_path / "out/b/logs/ingest.log").is_file()
    assert json.loads((tmp_path / "reports/fleet.json").read_text())["failed"] == f["failed"]
    table = (tmp_path / "reports/fleet.md").read_text()
    assert "| a | failed in job: OSError: " in table and "| b | failed in ingest: " in table


def test_a_robot_folder_name_of_250_characters_gets_its_scratch_folder(monkeypatch):
    """The scratch folder's prefix was the robot's whole name: a 250-character folder name (a file name may
    have 255) failed the job with OSError File name too long. Now the prefix is at most 40 of its characters."""
    monkeypatch.setattr(fleet, "run_logged", lambda stage, root: "stopped here")      # no stage needed
    name = "r" * 250
    r = fleet.calibrate_robot({"robot": name, "params": {"robot": {"model": "ur5"}}, "files": {"j.csv": b"j"}})
    assert (r["robot"], r["status"], r["stage"], r["reason"]) == (name, "failed", "ingest", "stopped here")
    assert r["files"]["campaign/j.csv"] == b"j" and "params.yaml" in r["files"]
    assert fleet.scratch_prefix("a|b c/" + name) == "fleet-a_b_c_" + "r" * 34 + "-"


def test_a_robot_folder_that_cannot_be_written_back_is_its_robots_row(tmp_path, monkeypatch):
    """A robot's folder that came back but could not be written to --out raised out of sweep.run (on_result):
    the robots after it never ran and no report was written. Now that robot fails in `write`, its earlier
    failure kept, and the reports are written."""
    root = a_fleet(tmp_path, monkeypatch)
    real = sweep.unpack

    def unpack(files, folder):
        if Path(folder).parent == tmp_path / "out":
            raise OSError(f"[Errno 28] No space left on device: '{folder}'")
        return real(files, folder)
    monkeypatch.setattr(sweep, "unpack", unpack)
    f = fleet.run_fleet(root, tmp_path / "out", "sequential", base=load_params())
    why = f["failed"]["b"]
    assert why.startswith(f"write: {tmp_path / 'out/b'}: [Errno 28] No space left") and "; before that: ingest: " in why
    assert "| b | failed in write: " in (tmp_path / "reports/fleet.md").read_text()


def test_threads_below_one_are_refused_when_the_command_is_parsed(tmp_path, monkeypatch, capsys):
    """`--threads -1` was taken: every robot's job then failed in torch (RuntimeError), a traceback; `0` meant
    the default. Now the command refuses it before anything runs (argparse: exit 2), as run_fleet does."""
    root = a_fleet(tmp_path, monkeypatch)
    with pytest.raises(SystemExit) as e:
        fleet.main(["run", str(root), "--out", "out", "--engine", "sequential", "--threads", "-1"])
    assert e.value.code == 2 and "--threads: -1: torch threads per robot must be >= 1" in capsys.readouterr().err
    with pytest.raises(ValueError, match="threads: 0: torch threads per robot must be >= 1"):
        fleet.run_fleet(root, "out", "sequential", threads=0)
    assert not (tmp_path / "out").exists() and not (tmp_path / "reports").exists()
    with pytest.raises(SystemExit) as e:                  # a review: `demo --robots 0` wrote nothing, exit 0
        fleet.main(["demo", str(tmp_path / "demo"), "--robots", "0"])
    assert e.value.code == 2 and "--robots: 0: a demo fleet's robots must be >= 1" in capsys.readouterr().err


def test_the_command_exits_1_when_a_robot_failed_its_reports_written(tmp_path, monkeypatch, capsys):
    """0 of 2 robots calibrated exited 0, so `dvc repro fleet/dvc.yaml` recorded a success. Now, the reports
    written, a robot that failed is a refusal (exit 1) that counts them and names each robot's step."""
    root = a_fleet(tmp_path, monkeypatch, ("a", "b"))
    (root / "a/params.yaml").write_text("- a list\n")
    with pytest.raises(SystemExit) as e:
        fleet.main(["run", str(root), "--out", "out", "--engine", "sequential"])
    err = capsys.readouterr().err
    assert e.value.code == 1 and "fleet: refused: 2 of 2 robot(s) failed (a in params, b in ingest), 0 calibrated" in err
    assert json.loads((tmp_path / "reports/fleet.json").read_text())["n_robots"] == 2
    ok = {"status": "ok", "model": "ur5", "n_points": 1, "seconds": 1.0, "files": {},
          "test_3d_mae_mm": {"nominal": 1.0, "calibrated": 0.2, "model": 0.1}}
    monkeypatch.setattr(fleet, "calibrate_robot", lambda job: {"robot": job["robot"], **ok})
    shutil.rmtree(root / "a")
    assert fleet.main(["run", str(root), "--out", "out", "--engine", "sequential"]) is None    # every robot: 0


def test_each_robots_output_folder_holds_this_run_only(tmp_path, monkeypatch):
    """Each robot was unpacked over its folder of the previous run: a robot that failed this time kept its old
    models and reports, as if calibrated. Now each robot's folder is cleared first (one refused in params has
    none)."""
    root = a_fleet(tmp_path, monkeypatch, ("a", "b"))
    (root / "a/params.yaml").write_text("- a list\n")
    for old in ("out/a/models/boter.pt", "out/b/models/boter.pt", "out/b/reports/index.md",
                f"out/a/{fleet.MARKER}", f"out/b/{fleet.MARKER}"):         # a previous fleet run's folders
        (tmp_path / old).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / old).write_text("the previous run's")
    f = fleet.run_fleet(root, tmp_path / "out", "sequential", base=load_params())
    assert f["failed"]["a"].startswith("params: ") and f["failed"]["b"].startswith("ingest: ")
    assert not (tmp_path / "out/a").exists()
    assert sorted(p.relative_to(tmp_path / "out/b").parts[0] for p in (tmp_path / "out/b").rglob("*")
                  if p.is_file()) == [fleet.MARKER, "campaign", "logs", "params.yaml"]


def test_a_folder_no_fleet_run_wrote_is_never_cleared(tmp_path, monkeypatch):
    """A review (2026-12-06): `fleet run myfleet --out .` with a robot folder named `data` deleted the project's
    data/ (its campaigns) to make room for the robot's output; a robot folder linked into --out lost its own
    campaign. Only a folder a fleet run wrote (its marker) is cleared; anything else is refused before any robot
    runs, named, nothing deleted."""
    root = a_fleet(tmp_path, monkeypatch, ("a", "data"))
    precious = tmp_path / "data/precious/measurements.csv"
    precious.parent.mkdir(parents=True)
    precious.write_text("x,y,z\n")
    with pytest.raises(ValueError, match=r"data not a fleet's output folder \(no \.fleet-output\): nothing cleared"):
        fleet.run_fleet(root, ".", "sequential", base=load_params())
    assert precious.read_text() == "x,y,z\n" and not (tmp_path / "a").exists()
    (tmp_path / "out").mkdir()
    (root / "data").rename(tmp_path / "out/data")                     # a robot folder that is a link into --out
    (root / "data").symlink_to(tmp_path / "out/data")
    with pytest.raises(ValueError, match=r"robot data's output folder .* robot data's own files"):
        fleet.run_fleet(root, "out", "sequential", base=load_params())
    assert (tmp_path / "out/data/params.yaml").exists()


@pytest.mark.parametrize("out, fleet_dir", [("fleet", "fleet"), ("fleet/robots", "fleet"), (".", "fleet")])
def test_an_out_folder_in_the_fleet_is_refused(tmp_path, monkeypatch, out, fleet_dir):
    """--out the fleet folder (or inside it) overwrote each robot's own params.yaml with its merged one, and
    the next run took the outputs for robots (campaign/campaign/...). Now it is refused, both named, as is an
    --out where a robot's folder would be the fleet folder (clearing it would delete the fleet)."""
    root = a_fleet(tmp_path, monkeypatch, ("b", "fleet"))
    before = (root / "b/params.yaml").read_text()
    with pytest.raises(ValueError, match=re.escape(f"--out {out}")) as e:
        fleet.run_fleet(fleet_dir, out, "sequential", base=load_params())
    assert f"fleet folder {fleet_dir}" in str(e.value)
    assert (root / "b/params.yaml").read_text() == before and sorted(p.name for p in root.iterdir()) == ["b", "fleet"]


def test_the_fleet_stage_declares_its_reports_and_ignores_bytecode():
    """fleet/dvc.yaml's deps are the whole pipeline/ folder: a Python run that wrote __pycache__ made `dvc status`
    say the fleet changed. Its reports/fleet.md was no declared output."""
    stage = yaml.safe_load((ROOT / "fleet/dvc.yaml").read_text())["stages"]["fleet"]
    outs = {k: v for o in stage["outs"] for k, v in o.items()}
    assert outs[str(fleet.FLEET_JSON)] == outs[str(fleet.FLEET_MD)] == {"cache": False}
    for path in ("pipeline/__pycache__/x.cpython-312.pyc", "pipeline/lib/y.pyc"):
        assert subprocess.run(["dvc", "check-ignore", "-q", path], cwd=ROOT).returncode == 0, path
    assert subprocess.run(["dvc", "check-ignore", "-q", "pipeline/commands/fleet.py"], cwd=ROOT).returncode == 1

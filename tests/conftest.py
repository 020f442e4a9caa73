"""Shared test setup: importing the package first pins the numeric libraries' threads and kernels
(pipeline/__init__.py), so tests compute what the stages compute.

`reproduced`: a fresh git+DVC copy of the project (the committed files, a small model) after `dvc repro`
(~1 min, once per test session, shared by the xdist workers: the first to need it builds it under a
file lock). `trained_project`: a project directory with trained artifacts, for the tests of what runs on
them (the service, the program compensator, the exports): the project itself when `dvc repro` has made
them and they are current; on a fresh clone (CI runs the tests before any repro), or after a change to
the code or params, `reproduced`. Both are read only: a test that changes a project works on a copy.
"""
import os
import shutil
import subprocess
from pathlib import Path

import pipeline  # noqa: F401  (first, before numpy loads: its kernels and threads are pinned there)
import pandas as pd
import pytest
import yaml
from filelock import FileLock

from pipeline.lib.learning.checkpoint import load_model
from pipeline.lib.learning.model import served
from pipeline.lib.learning.workspace import Workspace
from pipeline.lib.project.config import load_params, read_json
from pipeline.lib.reading.prepared import load_prepared

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
GIT_ENV = {**os.environ, "DVC_NO_ANALYTICS": "1", "GIT_AUTHOR_NAME": "ci", "GIT_AUTHOR_EMAIL": "ci@example.com",
           "GIT_COMMITTER_NAME": "ci", "GIT_COMMITTER_EMAIL": "ci@example.com"}
SMALL = {"model": {"d_model": 12, "n_head": 2, "n_layer": 1, "d_hidden": 32},
         "train": {"max_epochs": 12, "patience": 12}}
STAGES = ["ingest", "frame", "theory", "split", "calibrate", "parts", "train", "baselines", "evaluate", "export"]
NEEDED = ["models/boter.pt", "models/calibration.json", "models/workspace.json", "reports/frame.json",
          "data/interim/points.parquet", "data/interim/split.parquet", "reports/export.json"]


def background():
    """preexec_fn of the tests' long subprocesses (a `dvc repro`, 16 interpreters): nice 10, so that beside
    them, on the other xdist worker, the tests that time a service still get the CPU they measure."""
    os.nice(10)


def sh(cmd, cwd, check=True):
    """A shell command in cwd with a git identity and DVC's analytics off, niced (background); its
    CompletedProcess."""
    r = subprocess.run(cmd, cwd=cwd, env=GIT_ENV, shell=True, capture_output=True, text=True,
                       preexec_fn=background)
    if check and r.returncode:
        raise AssertionError(f"{cmd} failed ({r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
    return r


def pytest_collection_modifyitems(items):
    """The longest work first (a stable sort): the tests on `reproduced` (the first builds it), the other slow
    tests that need no trained project (the two-station project of the user's own campaign, bench real on
    Ray), the other tests that need none, then those on trained_project (on a fresh clone, `reproduced` too).
    xdist hands out the "serial" group (the largest scope) and then single tests in this order, so one worker
    builds `reproduced` from the start while the other runs the group's tests that need nothing of it (that
    project's repro, bench real on Ray: ~190 s, longer than the build) before those that do, rather than
    waiting on its lock (docs/results.md, the suite's timeline)."""
    def rank(item):
        names = set(item.fixturenames)
        if "reproduced" in names:
            return 0
        if names & {"trained_project", "in_trained_project"}:
            return 3
        return 1 if item.get_closest_marker("slow") else 2
    items.sort(key=rank)


def deep_update(d, u):
    for k, v in u.items():
        d[k] = deep_update(d.get(k, {}), v) if isinstance(v, dict) else v
    return d


def project_copy(dst: Path) -> Path:
    """A fresh git+DVC repo at dst holding the committed project files and a small-model params.yaml."""
    files = sh("git ls-files --cached --others --exclude-standard", ROOT).stdout.split()
    for f in files:
        if (ROOT / f).is_file() and not f.startswith("tests/"):
            (dst / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / f, dst / f)
    params = yaml.safe_load((dst / "params.yaml").read_text())
    (dst / "params.yaml").write_text(yaml.safe_dump(deep_update(params, SMALL), sort_keys=False))
    sh("git init -q && git add -A && git commit -qm init", dst)
    return dst


def repo_copy(src: Path, dst: Path) -> Path:
    """A copy of a git+DVC repo (work tree, git, DVC cache), without DVC's locks and temporary files."""
    shutil.copytree(src, dst, symlinks=True, ignore=lambda d, names: ["tmp"] if Path(d).name == ".dvc" else [],
                    dirs_exist_ok=True)
    return dst


def once(tmp_path_factory, name: str, make) -> str:
    """make(folder) -> str run once per test session, however many xdist workers ask: the first builds it
    under a file lock in the session's shared temporary folder, the others wait and reuse it."""
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent                                  # shared by the workers of one session
    folder, done = base / name, base / f"{name}.done"
    with FileLock(str(base / f"{name}.lock")):
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            done.write_text(str(make(folder)))
    return done.read_text()


@pytest.fixture(scope="session")
def reproduced(tmp_path_factory) -> Path:
    def make(folder):
        repo = project_copy(folder)
        sh("dvc repro", repo)
        return repo
    return Path(once(tmp_path_factory, "reproduced", make))


def served_model():
    """The model the project in the working directory serves (model.served: its physics alone where
    evaluate switched the network off, as with the suite's small model)."""
    return served(load_model("models/boter.pt"), Workspace.from_dict(read_json("models/workspace.json")).network)


def project_points(params: dict) -> pd.DataFrame:
    """The points of the project in the working directory, aligned as the stages see them, with their split."""
    return load_prepared(params["robot"], parts=False).points


@pytest.fixture(scope="session")
def trained_project(tmp_path_factory, request) -> Path:
    current = once(tmp_path_factory, "root_up_to_date", lambda _: "yes" if up_to_date(ROOT) else "no")
    return ROOT if current == "yes" else request.getfixturevalue("reproduced")


def up_to_date(root: Path) -> bool:
    """The project's own artifacts exist and `dvc status` finds STAGES current (artifacts a repro made
    before a code change are stale: the tests then build their own)."""
    if not all((root / p).exists() for p in NEEDED):
        return False
    r = subprocess.run(["dvc", "status", "--quiet", "--with-deps", *STAGES], cwd=root, capture_output=True,
                       env={**ENV, "DVC_NO_ANALYTICS": "1"})
    return r.returncode == 0


@pytest.fixture
def in_trained_project(trained_project, monkeypatch):
    """The working directory set to trained_project; its params."""
    monkeypatch.chdir(trained_project)
    return load_params()


def exit_code(main, argv, capsys) -> tuple[int, str]:
    """A command's exit code (0 when main returns) and what it said on stderr and stdout."""
    try:
        main(argv)
        code = 0
    except SystemExit as e:
        code = e.code
    out = capsys.readouterr()
    return code, out.err + out.out

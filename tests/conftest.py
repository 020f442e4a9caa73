"""Shared test setup: importing the package first pins BLAS threads (see pipeline/__init__.py).

`trained_project`: a project directory with trained artifacts, for the tests of what runs on them
(the service, the program compensator, the exports). The project itself when `dvc repro` has made
them and they are current; on a fresh clone, or after a change to the code or params, (CI runs the tests before any repro) the pipeline's stages, run on the
bundled twin campaign with a small model in a scratch directory (~1 min, once per session).
"""
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml

import pipeline  # noqa: F401
from pipeline.lib.artifacts import load_points
from pipeline.lib.config import load_params, read_json
from pipeline.lib.geometry import Calibration, aligned, theory_geometry
from pipeline.lib.robots import load_robot

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
SMALL = {"model": {"d_model": 12, "n_head": 2, "n_layer": 1, "d_hidden": 32},
         "train": {"max_epochs": 12, "patience": 12}}
STAGES = ["ingest", "frame", "theory", "split", "calibrate", "parts", "train", "baselines", "evaluate", "export"]
NEEDED = ["models/boter.pt", "models/calibration.json", "models/workspace.json", "reports/frame.json",
          "data/interim/points.parquet", "data/interim/split.parquet", "reports/export.json"]


def small_project(root: Path) -> Path:
    """The stages that make the trained artifacts, run on the bundled campaign with a small model."""
    params = load_params(ROOT / "params.yaml")
    for section, values in SMALL.items():
        params[section].update(values)
    for k in ("joints", "tracker"):
        params["ingest"][k] = str(ROOT / params["ingest"][k])
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    for stage in STAGES:
        subprocess.run([sys.executable, "-m", f"pipeline.{stage}"], cwd=root, env=ENV, check=True,
                       capture_output=True)
    return root


def project_points(params: dict) -> pd.DataFrame:
    """The points of the project in the working directory, aligned as the stages see them, with their split."""
    calibration = Calibration.from_dict(read_json("models/calibration.json"))
    nominal = theory_geometry(load_robot(params["robot"]), read_json("reports/frame.json")["tool_mm"])
    return aligned(load_points(), calibration, nominal)


@pytest.fixture(scope="session")
def trained_project(tmp_path_factory) -> Path:
    return ROOT if up_to_date(ROOT) else small_project(tmp_path_factory.mktemp("project"))


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

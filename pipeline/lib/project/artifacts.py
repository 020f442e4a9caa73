"""Where every pipeline artifact lives, and how a stage reads one back.

Paths are relative to a project's root, which every stage is handed (`root`; DVC runs
the stages with the root as working directory, HERE). Each file here is an output of
exactly one stage in dvc.yaml.
"""
from pathlib import Path

import pandas as pd

HERE = Path(".")                                      # the root when the working directory is the project
PARAMS_FILE = Path("params.yaml")
INTERIM, MODELS, REPORTS = Path("data/interim"), Path("models"), Path("reports")

INGEST_TABLE = INTERIM / "ingest.parquet"             # ingest
INGEST_JSON = REPORTS / "ingest.json"
CAMPAIGNS_DIR = INTERIM / "campaigns"                 # ingest_campaign@<name>: <name>.parquet
CAMPAIGNS_REPORTS = REPORTS / "campaigns"             #   and its <name>.json (dropped rows)
FRAME_JSON = REPORTS / "frame.json"                   # frame
POINTS_TABLE = INTERIM / "points.parquet"             # theory
THEORY_JSON = REPORTS / "theory.json"
SPLIT_TABLE = INTERIM / "split.parquet"               # split
SPLIT_JSON = REPORTS / "split.json"
CALIBRATED_GEOMETRY = MODELS / "calibration.json"     # calibrate
CALIBRATION_JSON = REPORTS / "calibration.json"
PARTS_JSON = MODELS / "parts.json"                    # parts: the per-joint error maps
PARTS_REPORT = REPORTS / "parts.json"
MODEL_WEIGHTS = MODELS / "boter.pt"                   # train
TRAIN_JSON = REPORTS / "train.json"
LIVE = REPORTS / "live"                               #   dvclive; its curves under live/plots/metrics
BASELINES_TABLE = INTERIM / "baselines.parquet"       # baselines
BASELINES_JSON = REPORTS / "baselines_train.json"
PREDICTIONS_TABLE = INTERIM / "predictions.parquet"   # evaluate
METRICS_JSON = REPORTS / "metrics.json"
HEADLINE_JSON = REPORTS / "headline.json"             #   the few numbers `dvc metrics show` / `dvc exp show` list
BASELINES_MD = REPORTS / "baselines.md"
WORKSPACE_JSON = MODELS / "workspace.json"           #   the trained workspace, the error scale
COMPENSATION_CSV = REPORTS / "compensation.csv"       # compensate (the Δθ table, and as parquet)
COMPENSATION_PARQUET = REPORTS / "compensation.parquet"
COMPENSATION_JSON = REPORTS / "compensation.json"
CONVERGENCE_CSV = REPORTS / "compensation_convergence.csv"
DRIVE_CSV = REPORTS / "drive_check.csv"
URDF_FILE = MODELS / "calibrated.urdf"                # export (docs/data-format.md, exports for the robot cell)
UR_YAML = MODELS / "ur_calibration.yaml"
MODEL_ONNX = MODELS / "model.onnx"
CONTROLLER_ONNX = MODELS / "controller.onnx"
CONTROLLER_PHYSICS_ONNX = MODELS / "controller_physics.onnx"
CONTROLLER_TCP_ONNX = MODELS / "controller_tcp.onnx"                  # the same two, with a tcp_mm input
CONTROLLER_PHYSICS_TCP_ONNX = MODELS / "controller_physics_tcp.onnx"
CONTROLLER_POSE_ONNX = MODELS / "controller_pose.onnx"                # a TCP's pose: six equations
ONNX_FILES = (MODEL_ONNX, CONTROLLER_ONNX, CONTROLLER_PHYSICS_ONNX, CONTROLLER_TCP_ONNX,   # onnx_model.export_all's,
              CONTROLLER_PHYSICS_TCP_ONNX, CONTROLLER_POSE_ONNX)                  # by their stems
EXPORT_JSON = REPORTS / "export.json"
VALIDATION_DIR = REPORTS / "validation"               # validate@<campaign>: <campaign>.json/.parquet
VALIDATION_JSON = REPORTS / "validation.json"         # validation (all campaigns)
VALIDATION_TABLE = REPORTS / "validation.parquet"
VALIDATION_HEADLINE = REPORTS / "validation_headline.json"   #   its mean errors, for `dvc metrics show`
TIMINGS = REPORTS / "timings"                         # every stage: <stage>.json, wall-clock times; not a
                                                      #   DVC output (git-ignored), so outputs hash the same


def rooted(root: Path, path: str | Path) -> str:
    """A path from params.yaml (relative to the project's root, or absolute) as this process opens it;
    unchanged at HERE, so what a stage records of it is the string params.yaml gave."""
    return str(path) if root == HERE or Path(path).is_absolute() else str(root / path)


def rooted_files(ingest: dict, root: Path) -> dict:
    """An ingest section whose joints and tracker files are opened from the project at `root`."""
    return {**ingest, "joints": rooted(root, ingest["joints"]), "tracker": rooted(root, ingest["tracker"])}


def as_given(report, ingest: dict, root: Path):
    """report (JSON-like) with the ingest section's files named as it gives them wherever this process
    opened them under root (rooted_files): a stage's record the same bytes wherever the project lies (a
    fleet's robot in a scratch folder, a benchmark's copy) as in place, where it is report itself."""
    names = {rooted(root, ingest[k]): str(ingest[k]) for k in ("joints", "tracker")}
    names = {opened: given for opened, given in names.items() if opened != given}

    def named(v):
        if isinstance(v, str):
            for opened, given in names.items():
                v = v.replace(opened, given)
            return v
        if isinstance(v, dict):
            return {k: named(x) for k, x in v.items()}
        return [named(x) for x in v] if isinstance(v, list) else v
    return named(report) if names else report


def project_owned(root: Path) -> list[Path]:
    """The files and folders at `root` a command's output may not replace: every output dvc.lock records, the
    settings and pipeline files, the committed campaigns and the benchmark records."""
    import yaml
    lock = root / "dvc.lock"
    stages = (yaml.safe_load(lock.read_text()) or {}).get("stages", {}) if lock.exists() else {}
    outs = [o["path"] for s in stages.values() for o in s.get("outs", [])]
    return [root / p for p in (PARAMS_FILE, "dvc.yaml", "dvc.lock", "data/raw", REPORTS / "bench", *outs)]


def require(root: Path, files) -> None:
    """Raise a ValueError naming each of `files` (artifact paths) missing from the project at `root`."""
    missing = [str(f) for f in files if not (root / f).exists()]
    if missing:
        raise ValueError(f"missing trained artifact(s) {', '.join(missing)} in {Path(root).resolve()}; "
                         "run `dvc repro` first")


def load_points(root: Path = HERE) -> pd.DataFrame:
    """points.parquet joined with its split column."""
    return pd.read_parquet(root / POINTS_TABLE).merge(pd.read_parquet(root / SPLIT_TABLE), on="point_id")

"""Shared plumbing: params.yaml, artifact paths, JSON writing, logging."""
import json
import logging
import sys
from pathlib import Path

import numpy as np
import yaml

PARAMS = Path("params.yaml")
INTERIM = Path("data/interim")
MODELS = Path("models")
REPORTS = Path("reports")

INGEST_TABLE = INTERIM / "ingest.parquet"
POINTS_TABLE = INTERIM / "points.parquet"
SPLIT_TABLE = INTERIM / "split.parquet"
PREDICTIONS_TABLE = INTERIM / "predictions.parquet"
BASELINES_TABLE = INTERIM / "baselines.parquet"
MODEL_WEIGHTS = MODELS / "boter.pt"
CALIBRATED_GEOMETRY = MODELS / "calibration.json"
FRAME_JSON = REPORTS / "frame.json"


def load_params(path: Path | str = PARAMS) -> dict:
    with open(path) as f:
        return yaml.safe_load(f)


def _jsonable(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON-serialisable: {type(o)}")


def write_json(path: Path | str, obj) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2, default=_jsonable) + "\n")


def read_json(path: Path | str):
    return json.loads(Path(path).read_text())


def logger(name: str) -> logging.Logger:
    """A stage's logger, named after its module even when run as `python -m pipeline.<stage>`."""
    if name == "__main__":
        spec = getattr(sys.modules["__main__"], "__spec__", None)
        name = spec.name if spec else name
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s",
                        datefmt="%H:%M:%S")
    return logging.getLogger(name.removeprefix("pipeline."))

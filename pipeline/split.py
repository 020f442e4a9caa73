"""Stage split: random 8:1:1 train/val/test split, seed 7, torch's random_split semantics.

Writes data/interim/split.parquet (point_id, split) and reports/split.json.
"""
import pandas as pd

from .lib.artifacts import POINTS_TABLE, SPLIT_JSON, SPLIT_TABLE
from .lib.config import load_params, logger, section, write_json
from .lib.splits import split_indices

log = logger(__name__)


def run(params: dict) -> dict:
    cfg = section(params, "split")
    ids = pd.read_parquet(POINTS_TABLE, columns=["point_id"])["point_id"]
    idx = split_indices(len(ids), cfg["fractions"], cfg["seed"])
    split = pd.Series("", index=ids.index)
    for name, rows in idx.items():
        split.iloc[rows] = name
    SPLIT_TABLE.parent.mkdir(parents=True, exist_ok=True)
    pd.DataFrame({"point_id": ids, "split": split}).to_parquet(SPLIT_TABLE, index=False)
    summary = {"seed": cfg["seed"], "fractions": cfg["fractions"],
               "counts": {k: len(v) for k, v in idx.items()}}
    write_json(SPLIT_JSON, summary)
    log.info("split %d points with seed %d: %s", len(ids), cfg["seed"], summary["counts"])
    return summary


if __name__ == "__main__":
    run(load_params())

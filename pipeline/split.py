"""Stage split: random 8:1:1 train/val/test split with torch's random_split semantics.

`random_split(range(n), [0.8, 0.1, 0.1], generator=Generator().manual_seed(7))`
gives 580/72/72 for 724 rows, as in the paper (SPEC.md stage 4).
"""
import pandas as pd
import torch
from torch.utils.data import random_split

from .config import POINTS_TABLE, REPORTS, SPLIT_TABLE, load_params, logger, write_json

log = logger(__name__)
SPLITS = ("train", "val", "test")


def split_indices(n: int, fractions, seed: int) -> dict[str, list[int]]:
    """Row indices of each split, exactly as torch.utils.data.random_split draws them."""
    parts = random_split(range(n), list(fractions), generator=torch.Generator().manual_seed(seed))
    return {name: list(p.indices) for name, p in zip(SPLITS, parts)}


def run(params: dict) -> dict:
    cfg = params["split"]
    ids = pd.read_parquet(POINTS_TABLE, columns=["point_id"])["point_id"]
    idx = split_indices(len(ids), cfg["fractions"], cfg["seed"])
    split = pd.Series("", index=ids.index)
    for name, rows in idx.items():
        split.iloc[rows] = name
    SPLIT_TABLE.parent.mkdir(parents=True, exist_ok=True)
    pd.DataFrame({"point_id": ids, "split": split}).to_parquet(SPLIT_TABLE, index=False)
    summary = {"seed": cfg["seed"], "fractions": cfg["fractions"],
               "counts": {k: len(v) for k, v in idx.items()}}
    write_json(REPORTS / "split.json", summary)
    log.info("split %d points with seed %d: %s", len(ids), cfg["seed"], summary["counts"])
    return summary


def main():
    run(load_params())


if __name__ == "__main__":
    main()

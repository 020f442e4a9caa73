"""Stage split: random 8:1:1 train/val/test split, seed 7, torch's random_split semantics.

Several training campaigns: each campaign is split on its own (8:1:1, seed 7,
in its table order), so every campaign has test points and a campaign's split
does not change when another campaign is added. One campaign: the paper's split. A pose measured again
(joints within splits.SAME_POSE_DEG) is one pose: its rows share a split (split.json's `repeated_poses`).

With `split.holdout` (a development check of extrapolation), the poses of a region of joint space
(splits.region: every listed joint above its quantile) are held out first, split "holdout": nothing
trains or validates on them, and evaluate reports every method on them beside the random test split.

Writes data/interim/split.parquet (point_id, split) and reports/split.json.
"""
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.lib.learning.splits import SAME_POSE_DEG, region, repeats, split_groups
from pipeline.lib.project.artifacts import HERE, POINTS_TABLE, SPLIT_JSON, SPLIT_TABLE
from pipeline.lib.project.cli import script, stage_main
from pipeline.lib.project.columns import CAMPAIGN, JOINTS_DEG, SPLITS
from pipeline.lib.project.config import for_stage, json_text, logger
from pipeline.lib.project.writing import write_together

log = logger(__name__)
PARAMS = ("split",)


def run(params: dict, root: Path = HERE) -> dict:
    cfg = for_stage(params, PARAMS)["split"]
    pts = pd.read_parquet(root / POINTS_TABLE, columns=["point_id", CAMPAIGN] + JOINTS_DEG)
    split = pd.Series("", index=pts.index)
    per, repeated = {}, {}
    for campaign in pts[CAMPAIGN].unique():
        rows = np.flatnonzero(pts[CAMPAIGN] == campaign)                           # positions, table order
        held = region(pts[JOINTS_DEG].to_numpy()[rows], cfg["holdout"])
        split.iloc[rows[held]] = "holdout"
        rows = rows[~held]
        groups = repeats(pts[JOINTS_DEG].to_numpy()[rows])        # a pose measured again: one split
        idx = split_groups(groups, cfg["fractions"], cfg["seed"])
        sizes = np.bincount(groups)                                # rows per pose
        empty = [k for k, v in idx.items() if not v]
        if empty:                                  # train, evaluate and the report need every split
            held_note = f" ({int(held.sum())} more held out by split.holdout)" if held.any() else ""
            poses = "" if len(sizes) == len(rows) else f" ({len(sizes)} poses, the others measured again)"
            raise ValueError(
                f"campaign {campaign!r}: its {len(rows)} points{poses}{held_note} split "
                f"{', '.join(f'{k} {len(v)}' for k, v in idx.items())} with split.fractions "
                f"{list(cfg['fractions'])}: the {' and '.join(empty)} split is empty. Measure more poses: "
                f"the ingest keeps at least 10, but the frame fit's outliers (reports/theory.json) are "
                f"dropped after it")
        for name, r in idx.items():
            split.iloc[rows[r]] = name
        per[campaign] = {**{k: len(v) for k, v in idx.items()}, "holdout": int(held.sum())}
        repeated[campaign] = {"rows": int(sizes[sizes > 1].sum()), "poses": int((sizes > 1).sum())}
        if repeated[campaign]["rows"]:
            log.info("campaign %s: %d rows are %d poses measured again (joints within %g°): each pose's rows in "
                     "one split", campaign, repeated[campaign]["rows"], repeated[campaign]["poses"], SAME_POSE_DEG)
    summary = {"seed": cfg["seed"], "fractions": cfg["fractions"], "holdout": cfg["holdout"],
               "counts": {k: sum(c[k] for c in per.values()) for k in SPLITS},
               "per_campaign": per, "same_pose_deg": SAME_POSE_DEG, "repeated_poses": repeated}
    for path in (root / SPLIT_TABLE, root / SPLIT_JSON):
        path.parent.mkdir(parents=True, exist_ok=True)
    table = pd.DataFrame({"point_id": pts["point_id"], "split": split}).to_parquet(None, index=False)
    write_together({root / SPLIT_TABLE: table, root / SPLIT_JSON: json_text(summary)})     # both, or neither
    log.info("split %d points with seed %d: %s", len(pts), cfg["seed"], summary["counts"])
    return summary


main = stage_main(__spec__.name, __doc__, run)         # main(argv=None, root=HERE)

if __name__ == "__main__":
    script(__spec__.name, main)

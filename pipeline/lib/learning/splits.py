"""The 8:1:1 split with torch's random_split semantics (docs/method.md stage 4).

`random_split(range(n), [0.8, 0.1, 0.1], generator=Generator().manual_seed(7))`
gives 580/72/72 for 724 rows, as in the paper.
"""
import numpy as np
import torch
from torch.utils.data import random_split

from pipeline.lib.project.columns import RANDOM_SPLITS


def region(q_deg: np.ndarray, cfg: dict | None) -> np.ndarray:
    """The held-out region of joint space (`split.holdout`): poses with every listed joint (1-based)
    above that joint's `quantile` over the poses given, (n,) bool; none when cfg is None."""
    if cfg is None:
        return np.zeros(len(q_deg), bool)
    cols = np.asarray(q_deg, float)[:, [j - 1 for j in cfg["joints"]]]
    return (cols > np.quantile(cols, cfg["quantile"], axis=0)).all(1)


def split_indices(n: int, fractions, seed: int) -> dict[str, list[int]]:
    """Row indices of each split, exactly as torch.utils.data.random_split draws them."""
    parts = random_split(range(n), list(fractions), generator=torch.Generator().manual_seed(seed))
    return {name: list(p.indices) for name, p in zip(RANDOM_SPLITS, parts)}

"""The 8:1:1 split with torch's random_split semantics (docs/method.md stage 4).

`random_split(range(n), [0.8, 0.1, 0.1], generator=Generator().manual_seed(7))`
gives 580/72/72 for 724 rows, as in the paper.

A pose measured again (its joints within SAME_POSE_DEG of another row's on every joint) is one pose: the
split draws over such groups (`repeats`), so its measurements share a split and a test point is never a
pose trained on. A campaign without repeats (the twin's, Series_C, gtpn-ur5) splits as the paper's.
"""
import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from torch.utils.data import random_split

from pipeline.lib.project.columns import RANDOM_SPLITS


def region(q_deg: np.ndarray, cfg: dict | None) -> np.ndarray:
    """The held-out region of joint space (`split.holdout`): poses with every listed joint (1-based)
    above that joint's `quantile` over the poses given, (n,) bool; none when cfg is None."""
    if cfg is None:
        return np.zeros(len(q_deg), bool)
    cols = np.asarray(q_deg, float)[:, [j - 1 for j in cfg["joints"]]]
    return (cols > np.quantile(cols, cfg["quantile"], axis=0)).all(1)


SAME_POSE_DEG = 0.05   # IPA Series_B's repeated joint configurations lie within 0.013° of each other (re-measured
                       # 0.002-2.3 mm apart, median 0.022), its next distinct poses 5.4° away; random poses degrees


def chained(x: np.ndarray, tol: float) -> np.ndarray:
    """A group number per row of x (n, k): rows within tol of each other on every column (chained) share one;
    groups numbered by their first row, so without such rows row k is group k. The distinct rows are linked,
    not the rows: a thousand copies of one row cost one."""
    x = np.asarray(x, float)
    if not len(x):
        return np.zeros(0, int)
    distinct, row = np.unique(x, axis=0, return_inverse=True)                   # (u, k), (n,)
    pairs = cKDTree(distinct).query_pairs(tol, p=np.inf, output_type="ndarray")  # (p, 2) within tol
    link = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(distinct),) * 2)
    labels = connected_components(link, directed=False)[1][row.ravel()]          # (n,)
    first = np.unique(labels, return_index=True)[1]                 # each label's first row
    rank = np.empty(len(first), int)
    rank[np.argsort(first)] = np.arange(len(first))
    return rank[labels]


def repeats(q_deg: np.ndarray) -> np.ndarray:
    """A group number per row (n,): rows whose joints lie within SAME_POSE_DEG of each other on every joint
    (chained) share one; groups numbered by their first row, so without repeats row k is group k."""
    return chained(q_deg, SAME_POSE_DEG)


def split_groups(groups: np.ndarray, fractions, seed: int) -> dict[str, list[int]]:
    """Row indices of each split, drawn over the groups (`repeats`) as split_indices draws over rows: every
    row of a group in its group's split; without repeats, split_indices itself."""
    groups = np.asarray(groups)
    n = int(groups.max()) + 1 if len(groups) else 0
    members = [[] for _ in range(n)]                                 # each group's rows, in table order
    for row, g in enumerate(groups):
        members[int(g)].append(row)
    idx = split_indices(n, fractions, seed)
    return {name: [r for g in gs for r in members[g]] for name, gs in idx.items()}


def split_indices(n: int, fractions, seed: int) -> dict[str, list[int]]:
    """Row indices of each split, exactly as torch.utils.data.random_split draws them."""
    parts = random_split(range(n), list(fractions), generator=torch.Generator().manual_seed(seed))
    return {name: list(p.indices) for name, p in zip(RANDOM_SPLITS, parts)}

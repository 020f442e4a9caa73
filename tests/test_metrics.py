"""Metrics against a hand computation (eqs. 27-42)."""
import math

import numpy as np
import pytest

from pipeline.lib.learning.metrics import drive_table, regression_metrics


def test_metrics_hand_computed():
    theory = np.zeros((2, 3))
    real = np.array([[1.0, 2.0, 1.0], [3.0, 0.0, 0.0]])
    pred = np.array([[1.0, 1.0, 0.0], [2.0, 0.0, 2.0]])
    # e = pred - real = [[0,-1,-1], [-1,0,2]]
    m = regression_metrics(pred, real, theory)
    assert m["x"] == pytest.approx({"mae": 0.5, "mse": 0.5, "rmse": math.sqrt(0.5), "r2": 0.5})
    assert m["y"] == pytest.approx({"mae": 0.5, "mse": 0.5, "rmse": math.sqrt(0.5), "r2": 0.5})
    # z: real Δ = (1, 0), mean 0.5, SS_tot 0.5, SS_res 1 + 4 = 5
    assert m["z"] == pytest.approx({"mae": 1.5, "mse": 2.5, "rmse": math.sqrt(2.5), "r2": -9.0})
    # 3D: |e| = √2, √5; MSE (2 + 5)/2; R² = 1 - 7 / (2 + 2 + 0.5)
    assert m["3d"] == pytest.approx({"mae": (math.sqrt(2) + math.sqrt(5)) / 2, "mse": 3.5,
                                     "rmse": math.sqrt(3.5), "r2": 1 - 7 / 4.5})


def test_r2_is_on_error_vectors_not_coordinates():
    rng = np.random.default_rng(0)
    theory = rng.uniform(-800, 800, (50, 3))
    real = theory + rng.normal(0, 1, (50, 3))
    assert regression_metrics(theory, real, theory)["3d"]["r2"] < 0.05   # nominal explains nothing
    assert regression_metrics(real, real, theory)["3d"]["r2"] == 1.0


def test_drive_table():
    target = np.zeros((4, 3))
    achieved = np.array([[0.1, 0, 0], [0, -0.6, 0], [0, 0, 0.2], [0.3, 0.4, 0]])
    t = drive_table(achieved, target)
    assert t["x"]["max"] == pytest.approx(0.3) and t["y"]["max"] == pytest.approx(0.6)
    assert t["x"]["min"] == 0.0
    assert t["3d"]["max"] == pytest.approx(0.6) and t["3d"]["mean"] == pytest.approx(1.4 / 4)
    assert t["within_tol_share"] == 0.75


def test_r2_of_a_one_point_split_is_null_not_minus_infinity():
    """A campaign of 10-19 poses leaves a val or test split of one point: its real errors do not vary, R² is
    undefined. It was -inf, written to metrics.json as `-Infinity` (not JSON) and shown as "R² -inf"."""
    import json

    from pipeline.lib.project.config import json_text
    m = regression_metrics(np.array([[1.0, 2.0, 3.0]]), np.array([[1.1, 2.0, 2.9]]), np.zeros((1, 3)))
    assert m["3d"]["mae"] == pytest.approx(math.sqrt(0.02))
    assert all(m[ax]["r2"] is None for ax in ("x", "y", "z", "3d"))
    json.loads(json_text(m), parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))


def test_stats_by_hand():
    """A mutation review: p95 read at another percentile passed. 0..100: mean 50, p95 95, max 100; none: None."""
    from pipeline.lib.learning.metrics import stats
    assert stats(np.arange(101.0)) == {"n": 101, "mean": 50.0, "p95": 95.0, "max": 100.0}
    assert stats(np.array([])) == {"n": 0, "mean": None, "p95": None, "max": None}


def test_the_split_is_the_seeds_and_the_held_out_region_the_top_quantile():
    """A mutation review: `split.seed` ignored (every test used 7) and the held-out region at 1 - quantile
    passed. The split is torch's random_split under the given seed; the region, by hand."""
    import torch
    from torch.utils.data import random_split

    from pipeline.lib.learning.splits import region, split_indices
    for seed in (7, 8):
        want = random_split(range(724), [0.8, 0.1, 0.1], generator=torch.Generator().manual_seed(seed))
        got = split_indices(724, [0.8, 0.1, 0.1], seed)
        assert [got[k] for k in ("train", "val", "test")] == [list(p.indices) for p in want]
        assert [len(v) for v in got.values()] == [580, 72, 72]
    assert split_indices(724, [0.8, 0.1, 0.1], 8)["test"] != split_indices(724, [0.8, 0.1, 0.1], 7)["test"]
    q = np.zeros((100, 6))
    q[:, 0], q[:, 1] = np.arange(100.0), np.arange(100.0)[::-1]
    assert np.flatnonzero(region(q, {"joints": [1], "quantile": 0.9})).tolist() == list(range(90, 100))
    assert not region(q, {"joints": [1, 2], "quantile": 0.9}).any()       # joint 2 high where joint 1 is low
    assert not region(q, None).any()

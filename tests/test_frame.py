"""Kabsch (eqs. 20-26): recovering a known transform, robust to misreads, refusing degenerate input."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.lib.frames import DegenerateFit, fit_frame, kabsch, robust_kabsch
from pipeline.lib.kinematics import fk_numpy
from pipeline.lib.robots import load_robot, nominal_robot

R_TRUE = Rotation.from_euler("zyx", [123.0, -17.0, 41.0], degrees=True).as_matrix()
T_TRUE = np.array([1200.0, -3050.0, 410.0])


def world(Q, rng, noise=0.03):
    return Q @ R_TRUE.T + T_TRUE + rng.normal(0, noise, Q.shape)


def test_kabsch_recovers_known_transform_from_noisy_points():
    rng = np.random.default_rng(0)
    Q = rng.uniform(-800, 800, (200, 3))
    R, t = kabsch(Q, world(Q, rng))
    angle = np.degrees(Rotation.from_matrix(R @ R_TRUE.T).magnitude())
    assert angle < 1e-3                                   # degrees (expected ≈ 2e-4)
    assert np.linalg.norm(t - T_TRUE) < 0.02              # mm
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_kabsch_exact_without_noise_and_proper_rotation_for_reflection():
    rng = np.random.default_rng(1)
    Q = rng.uniform(-1, 1, (10, 3))
    R, t = kabsch(Q, Q @ R_TRUE.T + T_TRUE)
    np.testing.assert_allclose(R, R_TRUE, atol=1e-12)
    np.testing.assert_allclose(t, T_TRUE, atol=1e-9)
    # a mirrored cloud has no proper rotation onto it: det(R) is still +1 (eq. 25)
    R, _ = kabsch(Q, Q * [1, 1, -1])
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_kabsch_refuses_collinear_and_too_few_points():
    line = np.outer(np.linspace(0, 1000, 20), [1.0, 2.0, -0.5])
    with pytest.raises(DegenerateFit, match="collinear"):
        kabsch(line, line + 5.0)
    with pytest.raises(DegenerateFit, match="at least 3 points for a rigid fit, got 2"):
        kabsch(line[:2], line[:2])


def test_robust_kabsch_flags_exactly_the_misreads():
    rng = np.random.default_rng(2)
    Q = rng.uniform(-800, 800, (300, 3))
    P = world(Q, rng, noise=0.5)                          # ~1 mm scatter like nominal DH
    bad = [5, 50, 123, 200, 299]
    P[bad] += rng.normal(0, 1, (5, 3)) * 15 + 8
    R, t, inliers, _ = robust_kabsch(Q, P, k=5, min_mm=3.0)
    assert sorted(np.flatnonzero(~inliers)) == bad
    assert np.degrees(Rotation.from_matrix(R @ R_TRUE.T).magnitude()) < 0.02


def test_frame_with_tool_estimation_recovers_tool():
    robot = nominal_robot("ur5")
    rng = np.random.default_rng(3)
    q = rng.uniform([-60, -120, -120, -180, 30, -180], [60, -30, 120, 0, 150, 180], (150, 6))
    tool_true = np.array([1.5, -2.0, 108.0])
    true = load_robot({"model": "ur5", "tool_mm": tool_true, "dh": None, "joint_limits_deg": None})
    P = world(fk_numpy(q, true), rng, noise=0.02)
    cfg = {"outlier_k": 5.0, "outlier_min_mm": 3.0, "estimate_tool": True, "tool_per_station": False,
           "robust_loss": "soft_l1", "robust_scale_mm": 0.5}
    fit = fit_frame(q, P, robot, cfg)
    np.testing.assert_allclose(fit["tool_mm"], tool_true, atol=0.02)
    np.testing.assert_allclose(fit["t"], T_TRUE, atol=0.05)
    assert fit["residual_mm"].mean() < 0.05

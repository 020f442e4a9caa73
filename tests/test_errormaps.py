"""Per-joint error maps (lib/robot/errormaps.py): a known joint error is recovered through the chain, the maps
fade where a joint was never measured, and they never take over a calibration parameter."""
import numpy as np
import pytest
import torch

from pipeline.lib.robot import errormaps as E
from pipeline.lib.robot.kinematics import DTYPE, fk, fk_jacobian, gravity_torques, nominal_geometry
from pipeline.lib.robot.robots import nominal_robot
from pipeline.lib.sim import twin as T

UR5 = nominal_robot("ur5")
G = nominal_geometry(UR5)
CFG = {"noise_mm": 0.01,
       "angle_map": {"joints": [1, 2, 3, 4, 5, 6], "knot_deg": 2.0, "prior_arcsec": 300.0, "smooth_arcsec": 50.0,
                     "reach_deg": 3.0, "fade_deg": 5.0},
       "load_map": {"joints": [], "knots": 12, "prior_arcsec": 300.0, "smooth_arcsec": 50.0},
       "thermal": {"column": None, "cte_per_k": 2.3e-5}}


def fine_error_rad(q_deg: np.ndarray) -> np.ndarray:
    """A known joint error: on joint 2, 40″ at 24 cycles/rev (a 15° period) and 25″ at 40 (9°); on joint
    3, 30″ at 30 cycles/rev."""
    q = np.radians(q_deg)
    out = np.zeros_like(q)
    out[:, 1] = np.radians((40 * np.sin(24 * q[:, 1] + 0.3) + 25 * np.sin(40 * q[:, 1] + 1.1)) / 3600)
    out[:, 2] = np.radians(30 * np.sin(30 * q[:, 2] + 2.0) / 3600)
    return out


def measured(q_deg: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return fk(torch.as_tensor(np.radians(q_deg) + fine_error_rad(q_deg), dtype=DTYPE), G).numpy()


def test_a_known_joint_error_is_recovered_through_the_chain():
    rng = np.random.default_rng(1)
    q_tr, q_te = T.sample_poses(1500, rng), T.sample_poses(200, rng)
    qt = torch.as_tensor(np.radians(q_tr), dtype=DTYPE)
    with torch.no_grad():
        p, J = (v.numpy() for v in fk_jacobian(qt, G))
        tau = gravity_torques(qt, G).numpy()
    maps, report, _ = E.fit(q_tr, tau, J, measured(q_tr) - p, CFG)
    g = {**G, **E.as_geometry(maps)}
    with torch.no_grad():
        before = np.linalg.norm(fk(torch.as_tensor(np.radians(q_te), dtype=DTYPE), G).numpy() - measured(q_te), axis=1)
        after = np.linalg.norm(fk(torch.as_tensor(np.radians(q_te), dtype=DTYPE), g).numpy() - measured(q_te), axis=1)
    assert before.mean() > 0.05 and after.mean() < 0.15 * before.mean()      # new poses, the error gone
    dth = E.joint_errors(torch.as_tensor(np.radians(q_te)), torch.zeros(len(q_te), 6), E.as_geometry(maps)).numpy()
    truth = fine_error_rad(q_te)
    assert np.abs(dth[:, 1] - truth[:, 1]).max() < np.radians(10 / 3600)       # within 10″ of 65″ features
    assert np.abs(dth[:, [0, 3, 4, 5]]).max() < np.radians(5 / 3600)            # nothing where there is none
    assert {b["joint"] for b in report["blocks"] if b["coef_rms_arcsec"] > 10} == {2, 3}


def test_the_maps_say_nothing_where_a_joint_was_never_measured():
    q = T.sample_poses(300, np.random.default_rng(2))                          # joint 1 within -60..60
    cover = E.coverage(q, [1], reach_deg=3.0, fade_deg=5.0)
    assert cover[0, 0] == 1.0 and cover[0, 90] == 0.0 and not cover[1:].any()
    g = E.as_geometry({"amap_coef": np.full((6, 180), np.radians(50 / 3600)), "amap_cover": cover})
    qq = torch.tensor(np.radians([[0.0] * 6, [90.0] + [0.0] * 5, [360.0] + [0.0] * 5]))
    d = E.joint_errors(qq, torch.zeros(3, 6), g).numpy()
    assert d[0, 0] == pytest.approx(np.radians(50 / 3600)) and d[1, 0] == 0.0     # measured; never measured
    assert d[2, 0] == pytest.approx(d[0, 0])                                         # 360° is 0°: the map repeats
    assert (d[:, 1:] == 0).all()


def test_covered_is_a_full_bin_and_a_load_inside_its_trained_range():
    """A mutation review: a bin half covered (the fade at the map's edge) counted as covered, and a load map's
    range three steps too wide, passed every test. A ramp 1, 0.5, 0 over joint 1's bins 10-12: 10.5° is
    covered, 11.5° not; a load map of 4 steps of 2 N·m from -3: -3 .. 5 N·m inside, 5.01 not."""
    cover = np.zeros((6, 360))
    cover[0, 10:13] = [1.0, 0.5, 0.0]
    q = np.zeros((3, 6))
    q[:, 0] = [10.5, 11.5, 12.5]
    assert E.angle_covered(cover, q)[:, 0].tolist() == [True, False, False]
    maps = {"lmap_lo": np.full(6, -3.0), "lmap_step": np.array([0, 2.0, 0, 0, 0, 0]), "lmap_coef": np.zeros((6, 7))}
    tau = np.zeros((4, 6))
    tau[:, 1] = [-3.0, 5.0, 5.01, -3.01]
    assert E.in_range(q[:1].repeat(4, 0), tau, maps)["load_map"].tolist() == [True, True, False, False]


def test_a_map_cannot_take_over_a_joint_offset_or_the_compliance():
    """A pure offset on joint 2 and a linear-in-torque error on joint 3 (what the calibration's offset
    and compliance hold), fitted beside those two calibration parameters (as the parts stage re-estimates
    the calibration's): the parameters take them, the maps stay empty."""
    rng = np.random.default_rng(3)
    q = T.sample_poses(800, rng)
    qt = torch.as_tensor(np.radians(q), dtype=DTYPE)
    with torch.no_grad():
        p, J = (v.numpy() for v in fk_jacobian(qt, G))
        tau = gravity_torques(qt, G).numpy()
    dq = np.zeros((len(q), 6))
    dq[:, 1] = np.radians(60 / 3600)
    dq[:, 2] = 2e-6 * tau[:, 2]
    r = np.einsum("nij,nj->ni", J, dq)
    cfg = {**CFG, "load_map": {**CFG["load_map"], "joints": [3]}}
    extra = np.stack([J[:, :, 1], J[:, :, 2] * tau[:, 2:3]], -1).reshape(-1, 2)   # offset2, compliance3
    maps, report, dx = E.fit(q, tau, J, r, cfg, extra)
    np.testing.assert_allclose(dx, [np.radians(60 / 3600), 2e-6], rtol=1e-3)
    for b in report["blocks"]:
        assert b["coef_rms_arcsec"] < 0.5, b

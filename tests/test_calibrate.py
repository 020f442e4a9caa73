"""Classical kinematic calibration: recovery, identifiability, robustness, the stage."""
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from scipy.spatial.transform import Rotation

from pipeline.lib.project.columns import ERR, JOINTS_DEG, MEAS, THEORY
from pipeline.lib.project.config import load_params, read_json, write_json
from pipeline.lib.robot import identify as C
from pipeline.lib.robot.geometry import Calibration
from pipeline.lib.robot.kinematics import DTYPE, fk, fk_numpy, nominal_geometry
from pipeline.lib.sim import twin as T
from pipeline.stages import calibrate

ROOT = Path(__file__).resolve().parents[1]
CFG = load_params(ROOT / "params.yaml")["calibrate"]


@pytest.fixture(scope="module")
def poses():
    q = T.sample_poses(200, np.random.default_rng(3))
    return torch.as_tensor(np.radians(q), dtype=DTYPE)


@pytest.fixture(scope="module")
def g0():
    return nominal_geometry(T.ur5())


def positions(q, g):
    with torch.no_grad():
        return fk(q, g).numpy()


@pytest.fixture(scope="module")
def truth(poses, g0):
    """A geometry with known errors on exactly the parameters the data can identify."""
    spec = C.parameter_spec(CFG)
    S = C.selectors(spec)
    J = C.jacobian(poses, torch.zeros(len(spec), dtype=DTYPE), g0, S).numpy()
    keep = C.identifiability(J, [s[0] for s in spec], CFG["rank_tol"])["keep"]
    rng = np.random.default_rng(11)
    size = lambda k, i: (rng.uniform(2e-5, 4e-4) if k == "compliance"       # rad/(N·m): 2500-50000 N·m/rad
                         else np.radians(rng.uniform(-0.1, 0.1)) if C.is_angular(k, i) else rng.uniform(-0.5, 0.5))
    x = np.array([size(k, i) for _, k, i in spec]) * keep
    g = {k: v.detach() for k, v in C.apply_deltas(torch.as_tensor(x), g0, S).items()}
    return g, dict(zip([s[0] for s in spec], x))


def test_recovers_positions_and_parameters_from_noiseless_data(poses, g0, truth):
    g_true, x_true = truth
    p = positions(poses, g_true)
    g, rep = C.identify(poses, p, g0, CFG)
    assert rep["before"]["mean_mm"] > 0.5
    assert np.abs(positions(poses, g) - p).max() < 1e-6            # mm
    for name in rep["identified"]:
        est = rep["estimates"][name]
        true = x_true[name] * (np.degrees(1.0) if est["unit"].startswith("deg") else 1.0)
        assert est["delta"] == pytest.approx(true, abs=1e-8 if est["unit"] != "deg/(N·m)" else 1e-11), name
    for k in g:                                                     # geometry itself, too
        np.testing.assert_allclose(g[k].numpy(), g_true[k].numpy(), atol=1e-8)


def test_a_parameter_off_by_a_known_amount_is_reported_with_that_sign(poses, g0):
    """A mutation review: every delta of calibration.json negated (apply_deltas subtracting) passed, the test
    above making its truth with apply_deltas too. Here the truth is edited by hand: a2 0.5 mm longer, joint
    3's offset 0.01° more; and the residual sigma is the plain residual over its degrees of freedom."""
    g = {k: v.clone() for k, v in g0.items()}
    g["a"][1] += 0.5
    g["offset"][2] += np.radians(0.01)
    p = positions(poses, g)
    fitted, rep = C.identify(poses, p, g0, CFG)
    assert rep["estimates"]["a2"]["delta"] == pytest.approx(0.5, abs=1e-6)
    assert rep["estimates"]["offset3"]["delta"] == pytest.approx(0.01, abs=1e-7)
    noisy = p + np.random.default_rng(5).normal(0, 0.05, p.shape)
    fitted, rep = C.identify(poses, noisy, g0, CFG)
    r = positions(poses, fitted) - noisy                              # (n, 3) at the solution
    dof = r.size - len(rep["identified"])
    assert rep["residual_sigma_mm"] == pytest.approx(np.sqrt((r ** 2).sum() / dof), rel=1e-9)


def test_the_orientation_rows_weigh_a_rotation_by_the_stated_noise(poses, g0):
    """A mutation review: the weight in arcsec-per-degree units, or left out of the rows, passed. 0.01 mm
    against 2″: 1031.3 mm/rad; a predicted orientation 10″ from the measured one is a row of 10″ times that."""
    w = C.orientation_weight({"mm": 0.01, "arcsec": 2.0})
    assert w == pytest.approx(0.01 / np.radians(2 / 3600)) and 1031 < w < 1032
    spec = C.parameter_spec(CFG)
    S, x = C.selectors(spec), torch.zeros(len(spec), dtype=DTYPE)
    p, R = C.predicted(poses, x, g0, S, None, orientation=True)
    off = torch.as_tensor(Rotation.from_rotvec([0, 0, np.radians(10 / 3600)]).as_matrix(), dtype=DTYPE)
    rows = C.residual_rows(poses, x, g0, S, None, None, p, R @ off, w).detach().numpy()
    assert np.abs(rows[:, :3]).max() == 0
    np.testing.assert_allclose(np.linalg.norm(rows[:, 3:], axis=1), w * np.radians(10 / 3600), rtol=1e-6)


def test_a_second_stations_correction_turns_the_probes_orientation_too(poses, g0):
    """A mutation review: the station's rotation left off the predicted orientation passed. Station b turned
    2° about z: its predicted positions and orientations are the first station's turned 2°."""
    spec = C.parameter_spec(CFG) + C.station_spec(["a", "b"])
    S, x = C.selectors(spec, 2), torch.zeros(len(spec), dtype=DTYPE)
    x[[s[0] for s in spec].index("b_rz")] = np.radians(2.0)
    at_b = torch.ones(len(poses), dtype=torch.long)
    p, R = C.predicted(poses, x, g0, S, at_b, orientation=True)
    p0, R0 = C.predicted(poses, torch.zeros_like(x), g0, S, None, orientation=True)
    Rz = Rotation.from_euler("z", 2.0, degrees=True).as_matrix()
    np.testing.assert_allclose(p.numpy(), p0.numpy() @ Rz.T, atol=1e-9)
    np.testing.assert_allclose(R.numpy(), Rz @ R0.numpy(), atol=1e-12)


def test_flags_redundant_parameters(poses, g0):
    p = positions(poses, g0)
    _, rep = C.identify(poses, p, g0, {**CFG, "params": ["d", "offset", "base"]})
    assert "d1" in rep["identified"] and "offset1" in rep["identified"]
    assert "base_tz" in rep["fixed"] and "d1" in rep["fixed"]["base_tz"]     # Tz(d1) == base tz
    assert "base_rz" in rep["fixed"] and "offset1" in rep["fixed"]["base_rz"]  # Rz(q1 + offset1)
    assert {"d3", "d4"} <= set(rep["fixed"])                        # parallel axes 2-3-4
    assert "offset6" in rep["fixed"]                                # tool 0: no effect at all
    assert rep["condition_number"] < 1e3 and rep["rank"] == len(rep["identified"])


def test_identified_set_on_the_full_model(poses, g0):
    _, rep = C.identify(poses, positions(poses, g0), g0, CFG)
    fixed = set(rep["fixed"])
    assert {"base_tz", "base_rz", "d3", "d4", "offset6", "alpha6"} <= fixed
    assert {"a2", "a3", "offset2", "offset3", "beta2", "beta3", "base_rx", "base_tx"} <= set(rep["identified"])
    assert len(rep["identified"]) + len(fixed) == rep["n_candidates"] == 41
    assert {"c2", "c3", "c4"} <= set(rep["identified"])
    assert "zero Jacobian" in rep["fixed"]["c1"]                    # vertical axis: no gravity torque
    assert "zero Jacobian" in rep["fixed"]["c6"]                    # flange mass on its own axis


@pytest.mark.parametrize("masses, rtol", [("twin", 0.005), ("published", 0.08)])
def test_elastic_calibration_recovers_the_twins_joint_stiffness(masses, rtol):
    """Noiseless twin campaign with gravity sag (no gear error): the stiffness of joints 2-5 comes back.

    With the twin's own link masses the only model difference is where the joint zeros were set
    (the twin's zero pose, absorbed by the offsets where they are identifiable): within 0.5 %.
    With the datasheet masses the calibration assumes (robots.py; the twin's arm is heavier at the
    flange, rounded elsewhere) the shape of the torques differs slightly: within 8 %.
    """
    e = T.sample_errors()
    e.update(gear_amp_deg=np.zeros((6, 2)), fine_amp_arcsec=np.zeros_like(e["fine_amp_arcsec"]),
             joint_sigma_deg=0.0, tracker_sigma_mm=0.0)
    twin = T.Twin(errors=e)
    q = twin.poses(400)
    g0 = nominal_geometry(T.ur5())
    if masses == "twin":
        g0.update(mass=torch.as_tensor(T.LINK_MASS), com=torch.as_tensor(T.LINK_COM))
    g, rep = C.identify(np.radians(q), twin.expected_position(q), g0, {**CFG, "loss": "linear"})
    assert rep["before"]["mean_mm"] > 0.3 and rep["after"]["mean_mm"] < 0.01
    k_true = 1.0 / twin.compliance
    k = rep["stiffness_Nm_per_rad"]
    assert sorted(k) == ["k2", "k3", "k4", "k5"]
    np.testing.assert_allclose([k[f"k{j}"] for j in (2, 3, 4, 5)], k_true[1:5], rtol=rtol)
    # without the compliance group the same data leave the sag unexplained
    _, rigid = C.identify(np.radians(q), twin.expected_position(q), g0,
                          {**CFG, "loss": "linear", "params": [p for p in CFG["params"] if p != "compliance"]})
    assert rigid["after"]["mean_mm"] > 10 * rep["after"]["mean_mm"]


def test_robust_loss_ignores_gross_outliers(poses, g0, truth):
    g_true, _ = truth
    p = positions(poses, g_true)
    rng = np.random.default_rng(5)
    bad = rng.choice(len(p), 5, replace=False)
    p_bad = p.copy()
    p_bad[bad] += rng.normal(0.0, 15.0, (5, 3))
    good = np.setdiff1d(np.arange(len(p)), bad)
    err = {}
    for loss in ("soft_l1", "linear"):
        g, _ = C.identify(poses, p_bad, g0, {**CFG, "loss": loss})
        err[loss] = np.linalg.norm(positions(poses, g) - p, axis=1)[good].mean()
    assert err["soft_l1"] < 0.05 and err["soft_l1"] < 0.1 * err["linear"]


def test_stage_writes_model_and_report(tmp_path, monkeypatch):
    """run() on interim tables made from the twin (base frame via a Kabsch fit)."""
    from pipeline.lib.robot.frames import kabsch
    twin = T.Twin()
    q = twin.poses(150)
    theory = fk_numpy(q, T.ur5())
    P = twin.drive(q, np.random.default_rng(0))
    R, t = kabsch(theory, P)
    meas = (P - t) @ R
    pts = pd.DataFrame({"point_id": [f"P{i:04d}" for i in range(len(q))], "campaign": "main", "station": "main"})
    pts[JOINTS_DEG], pts[THEORY], pts[MEAS], pts[ERR] = q, theory, meas, meas - theory
    split = pd.DataFrame({"point_id": pts["point_id"],
                          "split": np.where(np.arange(len(q)) < 120, "train",
                                            np.where(np.arange(len(q)) < 135, "val", "test"))})
    monkeypatch.chdir(tmp_path)
    Path("data/interim").mkdir(parents=True)
    pts.to_parquet("data/interim/points.parquet")
    split.to_parquet("data/interim/split.parquet")
    write_json("reports/frame.json", {"tool_mm": [0.0, 0.0, 0.0]})     # the frame stage's tool
    params = load_params(ROOT / "params.yaml")
    rep = calibrate.run(params)
    saved = read_json("reports/calibration.json")
    assert saved["identified"] == rep["identified"] and saved["splits"]["train"]["n"] == 120
    g = Calibration.from_dict(read_json("models/calibration.json")).geometry
    assert set(g) == {"d", "a", "alpha", "offset", "beta", "tool", "base", "compliance", "mass", "com"}
    assert all(v.dtype == DTYPE for v in g.values())
    e = np.linalg.norm(positions(torch.as_tensor(np.radians(q), dtype=DTYPE), g) - meas, axis=1)
    assert e[:120].mean() == pytest.approx(saved["splits"]["train"]["calibrated"]["mean_mm"])
    for s in ("train", "val", "test"):
        assert saved["splits"][s]["calibrated"]["mean_mm"] < 0.5 * saved["splits"][s]["nominal"]["mean_mm"]

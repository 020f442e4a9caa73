"""Large inputs: the gross-outlier check's reference points, and the compensation solved in chunks."""
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.lib import readers
from pipeline.lib.config import load_params
from pipeline.lib.kinematics import fk_numpy, nominal_geometry
from pipeline.lib.model import BoTER
from pipeline.lib.robots import load_robot, nominal_robot
from pipeline.lib.solvers import compensate

ROOT = Path(__file__).resolve().parents[1]
ROBOT_CFG = {"model": "ur5", "tool_mm": [10.0, -5.0, 120.0], "dh": None, "joint_limits_deg": None, "tcp": None}


def all_pairs_scores(m, t):
    """The rule written out: per point, the median over every other point of | |m_i-m_j| - |t_i-t_j| |."""
    out = np.empty(len(m))
    for i in range(len(m)):
        others = np.arange(len(m)) != i
        e = np.abs(np.linalg.norm(m[i] - m[others], axis=1) - np.linalg.norm(t[i] - t[others], axis=1))
        out[i] = np.median(e)
    return out


def points(n, seed=0):
    """Positions m (n, 3) mm and a slightly different set t: ties included (a repeated point)."""
    rng = np.random.default_rng(seed)
    m = rng.normal(0.0, 500.0, (n, 3)) + 1000.0
    t = m + rng.normal(0.0, 1.0, (n, 3))
    t[::7] += 30.0
    m[-1], t[-1] = m[0], t[0]
    return m, t


@pytest.mark.parametrize("n", [2, 3, 10, 11, 599, 600, 724, 1001, 4096])
def test_up_to_4096_points_the_scores_are_the_all_pairs_ones_exactly(n):
    m, t = points(n, seed=n)
    assert np.array_equal(readers.consistency_scores(m, t), all_pairs_scores(m, t))


def test_beyond_4096_points_each_is_scored_against_a_fixed_subset():
    n = 6000
    ref = readers.reference_points(n)
    assert len(ref) == len(set(ref)) == readers.REFERENCE_POINTS and np.all(np.diff(ref) > 0)
    assert np.array_equal(ref, readers.reference_points(n))            # seeded: the same every run
    m, t = points(n)
    s = readers.consistency_scores(m, t)
    for i in [0, 1, ref[0], ref[-1], n - 1, *np.random.default_rng(1).integers(0, n, 20)]:
        j = ref[ref != i]                                                # not against itself
        e = np.abs(np.linalg.norm(m[i] - m[j], axis=1) - np.linalg.norm(t[i] - t[j], axis=1))
        assert s[i] == np.median(e)


def write_campaign(folder, n, outliers, seed=0):
    """joints.csv and tracker.csv of n noiseless UR5 points in a tracker frame, `outliers` moved 200 mm."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-170.0, 170.0, (n, 6))
    m = fk_numpy(q, load_robot(ROBOT_CFG)) @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).T
    m += [1500.0, -300.0, 800.0]
    m[outliers, 1] += 200.0
    ids = [f"P{i + 1:05d}" for i in range(n)]
    (folder / "joints.csv").write_text("point_id,j1_deg,j2_deg,j3_deg,j4_deg,j5_deg,j6_deg\n" + "".join(
        f"{i}," + ",".join(repr(float(v)) for v in row) + "\n" for i, row in zip(ids, q)))
    (folder / "tracker.csv").write_text("Name,X,Y,Z\n" + "".join(
        f"{i}," + ",".join(repr(float(v)) for v in row) + "\n" for i, row in zip(ids, m)))
    return ids


def ingest_cfg(folder) -> dict:
    """The project's ingest settings for the campaign in `folder`."""
    cfg = load_params(ROOT / "params.yaml")["ingest"]
    return {**cfg, "joints": str(folder / "joints.csv"), "tracker": str(folder / "tracker.csv"),
            "columns": {"point_id": None, "joints": None, "position": None, "orientation": None, "marker": None},
            "gross_outlier_mm": 50.0}


def test_a_gross_outlier_among_6000_points_is_found_and_progress_is_logged(tmp_path, caplog):
    ids = write_campaign(tmp_path, 6000, [17, 4321])
    cfg = ingest_cfg(tmp_path)
    with caplog.at_level("INFO"):
        df, s = readers.ingest(cfg, load_robot(ROBOT_CFG))
    assert {d["point_id"] for d in s["dropped"]} == {ids[17], ids[4321]}
    assert s["dropped_counts"] == {"gross_outlier": 4} and s["n_kept"] == len(df) == 5998
    assert s["gross_outlier"]["reference_points"] == 4096 and s["gross_outlier"]["n_dropped"] == 2
    assert s["gross_outlier"]["max_mm"] > 50.0 and s["gross_outlier"]["median_mm"] < 1e-6
    lines = caplog.text
    assert "6000 points paired" in lines
    assert "gross-outlier check: 6000 of 6000 points scored against 4096 reference points" in lines


def test_up_to_4096_points_the_report_has_no_reference_points_key(tmp_path):
    write_campaign(tmp_path, 40, [3])
    cfg = ingest_cfg(tmp_path)
    _, s = readers.ingest(cfg, load_robot(ROBOT_CFG))
    assert set(s["gross_outlier"]) == {"limit_mm", "median_mm", "max_mm", "n_dropped"}


@pytest.fixture(scope="module")
def model():
    """A small BoTER with a large network term (α = 1)."""
    torch.manual_seed(0)
    m = BoTER(nominal_geometry(nominal_robot("ur5")), d_model=12, n_layer=1, n_head=2, d_hidden=32, mask="spi",
              head="resnet", encoder=True, alpha0=0.1, dropout=0.0, fade_to=None)
    with torch.no_grad():
        m.alpha.fill_(1.0)
    return m.eval()


@pytest.mark.parametrize("solver,jacobian_of", [("lm", "physics"), ("lm", "model"), ("adam", "physics")])
def test_a_chunked_solve_gives_one_batch_numbers(model, solver, jacobian_of, caplog):
    """70 points in blocks of at most 16, solved on every core (solvers.in_blocks), give the numbers of
    one batch bit for bit: q, prediction, iterations, convergence and (lm) the history."""
    rng = np.random.default_rng(0)
    q_true = rng.uniform([-60, -120, 30, -150, 40, -90], [60, -40, 120, -30, 140, 90], (70, 6))
    with torch.no_grad():
        target = model(torch.as_tensor(np.radians(q_true)))[0].numpy()
    q0 = q_true + rng.uniform(-0.1, 0.1, (70, 6))
    q0[5] += 40.0                                                       # a point that takes long
    cfg = {"lr": 1e-3, "max_iter": 60, "tol_mse": 1e-4, "tol_mm": 1e-3, "jacobian_of": jacobian_of}
    robot = nominal_robot("ur5")
    whole = compensate(model, q0, target, cfg, robot, solver)
    with caplog.at_level("INFO"):
        chunked = compensate(model, q0, target, cfg, robot, solver, chunk=16)
    for a, b in zip(whole[:4], chunked[:4]):                            # q, pred, iterations, converged
        assert np.array_equal(a, b)
    if solver == "lm":
        assert np.array_equal(whole[4], chunked[4])                     # history
    assert "compensate: 70 of 70 points solved" in caplog.text              # progress, a line per block
    assert compensate(model, q0, target, cfg, robot, solver, history=False)[4] is None

"""Large inputs: the gross-outlier check's reference points, and the compensation solved in chunks."""
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.lib.learning.model import BoTER
from pipeline.lib.project.config import load_params
from pipeline.lib.project.writing import csv_text
from pipeline.lib.reading import readers
from pipeline.lib.robot.kinematics import fk_numpy, nominal_geometry
from pipeline.lib.robot.robots import load_robot, nominal_robot
from pipeline.lib.runtime.solvers import compensate

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


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_csv_text_is_pandas_to_csv_byte_for_byte(data):
    """The program's fast CSV writer equals pandas' to_csv on what a Δθ table holds (floats of any sign and
    size, -0.0, inf, ints, bools, ids), and on what it must hand back to pandas (NaN, text to quote)."""
    n = data.draw(st.integers(1, 30))
    floats = st.floats(allow_nan=True, allow_infinity=True, width=64)
    text = st.text(alphabet="ab:,\" \n", min_size=0, max_size=4)
    df = pd.DataFrame({"point_id": data.draw(st.lists(text, min_size=n, max_size=n)),
                       "x": data.draw(st.lists(floats, min_size=n, max_size=n)),
                       "y": np.array(data.draw(st.lists(st.floats(-1e6, 1e6), min_size=n, max_size=n))),
                       "iterations": data.draw(st.lists(st.integers(-5, 10**6), min_size=n, max_size=n)),
                       "converged": data.draw(st.lists(st.booleans(), min_size=n, max_size=n))})
    fmt = data.draw(st.sampled_from(["%.6f", "%.4f", "%.9f"]))
    assert csv_text(df, fmt) == df.to_csv(index=False, float_format=fmt, lineterminator="\n")


def test_csv_text_takes_the_fast_path_on_a_plain_table(monkeypatch):
    """A Δθ-like table (ids, floats, ints, bools) never reaches pandas' writer, and its text is pandas'."""
    rng = np.random.default_rng(0)
    df = pd.DataFrame({"point_id": [f"W{i:03d}" for i in range(50)], "x": rng.normal(0, 500, 50),
                       "iterations": rng.integers(0, 9, 50), "converged": rng.random(50) > 0.5})
    want = df.to_csv(index=False, float_format="%.6f", lineterminator="\n")
    monkeypatch.setattr(pd.DataFrame, "to_csv", lambda *a, **k: pytest.fail("fell back to pandas"))
    assert csv_text(df) == want


def test_nearest_distance_in_chunks_is_the_plain_formula_exactly():
    """The workspace distance, chunked and in place (numpy) or chunked (torch), equals the one-line
    formula min_j |wrapped(q - ref_j)| bit for bit, at the wrap's edges too (±180°, multiples of 360°)."""
    from pipeline.lib.learning.workspace import JOINTS, nearest_distance, wrapped
    rng = np.random.default_rng(3)
    ref = rng.uniform(-360, 360, (300, 6))
    q = np.concatenate([rng.uniform(-360, 360, (700, 6)), ref[:50] + 360.0, ref[:50] - 180.0,
                        np.full((20, 6), -180.0), np.full((20, 6), 360.0)])
    plain = np.sqrt((wrapped(q[:, None, JOINTS] - ref[None, :, JOINTS]) ** 2).sum(-1)).min(1)
    assert np.array_equal(nearest_distance(q, ref), plain)
    assert np.array_equal(nearest_distance(q, ref, chunk=7), plain)
    own = np.sqrt((wrapped(ref[:, None, JOINTS] - ref[None, :, JOINTS]) ** 2).sum(-1))
    np.fill_diagonal(own, np.inf)
    assert np.array_equal(nearest_distance(ref, ref, chunk=7, leave_one_out=True), own.min(1))
    tq, tr = torch.as_tensor(q), torch.as_tensor(ref)
    assert torch.equal(nearest_distance(tq, tr, chunk=1024), nearest_distance(tq, tr))
    assert np.allclose(nearest_distance(tq, tr).numpy(), plain, rtol=0, atol=1e-12)


def test_the_kd_tree_candidates_give_the_brute_force_distance_to_the_bit():
    """From TREE_ROWS poses on, the periodic KD-tree picks NEAREST_K candidates and the formula the nearest:
    the same bits as the formula over all of ref, numpy and torch (its gradient too), near the training
    poses and far, across the wrap, with duplicated references; a NaN pose still answers NaN."""
    from pipeline.lib.learning.workspace import JOINTS, TREE_ROWS, candidates, nearest_distance, wrapped
    rng = np.random.default_rng(5)
    ref = rng.uniform(-200, 200, (576, 6))
    ref[100:110] = ref[:10]                                                  # duplicates: exact ties
    q = np.concatenate([ref[rng.integers(0, 576, 3000)] + rng.normal(0, 2, (3000, 6)),
                        rng.uniform(-720, 720, (1000, 6)), ref[:50] + 360.0, ref[50:100] - 180.0])
    assert candidates(q[:, JOINTS], ref[:, JOINTS]) is not None and len(q) >= TREE_ROWS
    plain = np.sqrt((wrapped(q[:, None, JOINTS] - ref[None, :, JOINTS]) ** 2).sum(-1)).min(1)
    assert np.array_equal(nearest_distance(q, ref), plain)
    tq = torch.as_tensor(q).requires_grad_(True)
    brute = torch.cat([wrapped(tq[s:s + 256, None, JOINTS] - torch.as_tensor(ref)[None, :, JOINTS]).norm(dim=-1)
                       .min(1).values for s in range(0, len(q), 256)])
    tree = nearest_distance(tq, torch.as_tensor(ref))
    assert torch.equal(tree, brute)
    g_tree, = torch.autograd.grad(tree.sum(), tq)
    g_brute, = torch.autograd.grad(brute.sum(), tq)
    assert torch.equal(g_tree, g_brute)
    q[7, 2] = np.nan
    assert np.isnan(nearest_distance(q, ref)[7]) and np.array_equal(np.delete(nearest_distance(q, ref), 7),
                                                                    np.delete(plain, 7))


@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(st.floats(-1e6, 1e6).map(repr), st.from_regex(r"[ +-]?[0-9]{0,3}[.,]?[0-9]{0,3}(e-?[0-9])? ?",
                                                                         fullmatch=True),
                          st.sampled_from(["", " ", "nan", "inf", "1e999", "1\n2", "1.", ".5", "٣", "1,5", "--1"])),
                min_size=1, max_size=8),
       st.sampled_from([".", ","]))
def test_parse_column_reads_a_column_as_parse_number_reads_each_cell(cells, decimal):
    """The waypoint reader's column-at-once parse gives parse_number's values where every cell is a finite
    number, and hands the column back (None) otherwise, so the cell-by-cell rule names the bad cell."""
    each = [readers.parse_number(c, decimal) for c in cells]
    fine = all(err is None and np.isfinite(v) for v, err in each)
    got = readers.parse_column(cells, decimal)
    if fine:
        assert got is not None and np.array_equal(got, [v for v, _ in each])
    else:
        assert got is None

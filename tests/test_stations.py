"""Several campaigns from several tracker stations: one frame per station, the robot identified jointly."""
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from scipy.spatial.transform import Rotation

from pipeline.lib.learning.splits import split_indices
from pipeline.lib.project.columns import CAMPAIGN, ERR, JOINTS_DEG, MEAS, MEAS_Q, STATION, THEORY
from pipeline.lib.project.config import load_params, read_json
from pipeline.lib.reading.presets import merged_params
from pipeline.lib.robot import identify as C
from pipeline.lib.robot.frames import FrameFitError, fit_frames
from pipeline.lib.robot.geometry import Calibration, aligned, at_temperature, theory_geometry
from pipeline.lib.robot.kinematics import DTYPE, fk, nominal_geometry, rigid_xyz
from pipeline.lib.robot.robots import load_robot
from pipeline.lib.robot.robots import nominal_robot
from pipeline.lib.sim import twin as T
from pipeline.stages import calibrate, frame, ingest, split, theory

ROOT = Path(__file__).resolve().parents[1]
PARAMS = load_params(ROOT / "params.yaml")
CFG = PARAMS["calibrate"]
STATION_B = T.sample_tracker_pose(T.STATION_B["seed"])


def rigid(R, t, p):
    return p @ np.asarray(R).T + np.asarray(t)


def noiseless_twin(gear=False) -> dict:
    """The twin's errors without noise; without gear=True also without the joints' gear error and fine
    structure (what the rigid calibration cannot model)."""
    e = T.sample_errors()
    e.update(joint_sigma_deg=0.0, tracker_sigma_mm=0.0)
    if not gear:
        e["gear_amp_deg"] = np.zeros((6, 2))
        e["fine_amp_arcsec"] = np.zeros_like(e["fine_amp_arcsec"])
    return e


def test_frames_of_two_stations_and_the_shared_tool_are_recovered_exactly():
    """A perfect arm with a known marker offset, measured from two tracker poses, no noise:
    both frames and the tool come back (the tool estimated from a zero start)."""
    e = T.zero_errors()
    e["tool_mm"] = np.array([3.0, -2.0, 40.0])
    a, b = T.Twin(errors=e), T.Twin(errors=e, tracker_pose=STATION_B)
    qa = T.sample_poses(200, np.random.default_rng(1))
    qb = T.sample_poses(100, np.random.default_rng(2), region="side")
    P = np.vstack([a.to_tracker(a.expected_position(qa)), b.to_tracker(b.expected_position(qb))])
    P[5] += [0.0, 30.0, 0.0]                                  # a gross misread of station a
    station = np.array(["a"] * 200 + ["b"] * 100)
    fit = fit_frames(np.vstack([qa, qb]), P, station, nominal_robot("ur5"), PARAMS["frame"] | {"estimate_tool": True})
    assert list(fit["stations"]) == ["a", "b"]
    assert np.flatnonzero(~fit["inliers"]).tolist() == [5]
    np.testing.assert_allclose(fit["tool_mm"], e["tool_mm"], atol=1e-6)
    for twin, s in ((a, "a"), (b, "b")):
        f = fit["stations"][s]
        angle = np.degrees(Rotation.from_matrix(f["R"].T @ twin.R).magnitude())
        assert angle < 1e-7 and np.abs(f["t"] - twin.t).max() < 1e-5, s
    assert fit["residual_mm"][fit["inliers"]].max() < 1e-6


def test_a_tool_per_station_is_recovered_exactly_when_asked_for():
    """Station b measured a second marker 30 mm away: frame.tool_per_station fits both tools
    (and both frames) exactly; forced to share one tool, the fit cannot explain station b."""
    e = T.zero_errors()
    e["tool_mm"] = np.array([3.0, -2.0, 40.0])
    tool_b = e["tool_mm"] + [10.0, 0.0, -28.0]
    a, b = T.Twin(errors=e), T.Twin(errors={**e, "tool_mm": tool_b}, tracker_pose=STATION_B)
    qa = T.sample_poses(200, np.random.default_rng(1))
    qb = T.sample_poses(100, np.random.default_rng(2), region="side")
    P = np.vstack([a.to_tracker(a.expected_position(qa)), b.to_tracker(b.expected_position(qb))])
    station = np.array(["a"] * 200 + ["b"] * 100)
    cfg = PARAMS["frame"] | {"estimate_tool": True, "tool_per_station": True}
    fit = fit_frames(np.vstack([qa, qb]), P, station, nominal_robot("ur5"), cfg)
    np.testing.assert_allclose(fit["stations"]["a"]["tool_mm"], e["tool_mm"], atol=1e-6)
    np.testing.assert_allclose(fit["stations"]["b"]["tool_mm"], tool_b, atol=1e-6)
    np.testing.assert_allclose(fit["tool_mm"], e["tool_mm"], atol=1e-6)
    assert np.abs(fit["stations"]["b"]["t"] - b.t).max() < 1e-5
    assert fit["residual_mm"].max() < 1e-6
    with pytest.raises(FrameFitError, match=r"station 'b'.*rms 2\d\.\d mm.*frame.tool_per_station"):
        fit_frames(np.vstack([qa, qb]), P, station, nominal_robot("ur5"), cfg | {"tool_per_station": False})
    with pytest.raises(ValueError, match="frame.tool_per_station: true needs frame.estimate_tool: true"):
        fit_frames(qa, P[:200], station[:200], nominal_robot("ur5"), cfg | {"estimate_tool": False})


@pytest.fixture(scope="module")
def poses():
    qa = T.sample_poses(200, np.random.default_rng(3))
    qb = T.sample_poses(100, np.random.default_rng(4), region="side")
    return torch.as_tensor(np.radians(np.vstack([qa, qb])), dtype=DTYPE)


def test_identify_recovers_a_known_station_correction_with_the_robot(poses):
    """Station b's points are off by a small rigid motion (what a frame fitted with nominal
    kinematics leaves): identified jointly with the robot's errors, to 1e-8."""
    g0 = nominal_geometry(T.ur5())
    spec = C.parameter_spec(CFG)
    S = C.selectors(spec)
    x = np.zeros(len(spec))
    for k, (name, key, i) in enumerate(spec):                 # known errors on some parameters
        if name in ("a2", "a3", "d5", "alpha3", "offset2", "beta2", "tool_y", "base_tx"):
            x[k] = np.radians(0.05) if C.is_angular(key, i) else 0.4
    g_true = C.apply_deltas(torch.as_tensor(x), g0, S)
    d_true = torch.tensor([np.radians(0.08), np.radians(-0.05), np.radians(0.02), 0.3, -0.6, 0.2], dtype=DTYPE)
    with torch.no_grad():
        p = fk(poses, g_true)
        R, t = rigid_xyz(d_true)
        p[200:] = p[200:] @ R.T + t
    station = np.r_[np.zeros(200, int), np.ones(100, int)]
    g, rep = C.identify(poses, p.numpy(), g0, {**CFG, "loss": "linear"}, station, ["a", "b"])
    assert rep["after"]["max_mm"] < 1e-6
    np.testing.assert_allclose(rep["stations"]["b"], d_true.numpy(), atol=1e-8)
    assert rep["stations"]["a"] == [0.0] * 6
    assert {"b_rx", "b_tz"} <= set(rep["identified"])
    assert isinstance(rep["fixed_because_of_stations"], dict)
    # lumped into one station, the same data cannot be explained
    _, lumped = C.identify(poses, p.numpy(), g0, {**CFG, "loss": "linear"})
    assert lumped["after"]["mean_mm"] > 0.05


@pytest.mark.parametrize("tool_b", [None, [0.0, 12.0, -25.0]], ids=["shared tool", "tool per station"])
def test_two_twin_stations_recovered_through_frame_and_calibrate_stages(tmp_path, monkeypatch, tool_b):
    """Noiseless twin (no gear error) from two tracker poses, through ingest, frame, theory,
    split and calibrate: each station's frame (frame stage ∘ its correction) maps the calibrated
    model onto its tracker readings, and station b's pose relative to a is the true one, to
    < 0.05 mm and 0.001° (in the calibrated base frame, which differs from the twin's base by
    the gauge d1/offset1/base the calibration cannot see: measured on station a). Told that
    station b measured another marker (frame.tool_per_station), its tool offset comes back too."""
    e = noiseless_twin()
    a = T.Twin(errors=e)
    dtool = np.zeros(3) if tool_b is None else np.asarray(tool_b)
    b = T.Twin(errors={**e, "tool_mm": e["tool_mm"] + dtool}, tracker_pose=STATION_B)
    qa = a.poses(300)
    qb = T.sample_poses(150, np.random.default_rng(5), region="side")
    monkeypatch.chdir(tmp_path)
    for d, twin, q, pre in (("a", a, qa, "P"), ("b", b, qb, "B")):
        Path(d).mkdir()
        ids = [f"{pre}{i:04d}" for i in range(len(q))]
        pd.DataFrame(q, columns=JOINTS_DEG).assign(point_id=ids).to_csv(f"{d}/joints.csv", index=False,
                                                                        float_format="%.9f")
        P = twin.to_tracker(twin.expected_position(q))
        pd.DataFrame(P, columns=["X", "Y", "Z"]).assign(Name=ids).to_csv(f"{d}/tracker.csv", index=False,
                                                                       float_format="%.9f")
    params = json.loads(json.dumps(PARAMS))
    params["ingest"].update(joints="a/joints.csv", tracker="a/tracker.csv")
    params["ingest"]["columns"]["orientation"] = None               # positions only
    params["campaigns"] = {"name": "front", "station": "a", "more": {
        "side": {"ingest": {"joints": "b/joints.csv", "tracker": "b/tracker.csv"}, "station": "b"}}}
    params["calibrate"]["loss"] = "linear"
    if tool_b is not None:
        params["frame"].update(estimate_tool=True, tool_per_station=True)
    ingest.run_campaign(params, "side")
    ingest.run(params)
    frame.run(params)
    theory.run(params)
    split.run(params)
    calibrate.run(params)

    rep = read_json("reports/calibration.json")
    fr = read_json("reports/frame.json")
    assert list(fr["stations"]) == ["a", "b"] and fr["R"] == fr["stations"]["a"]["R"]
    cal = Calibration.from_dict(read_json("models/calibration.json"))
    g = cal.geometry
    # each station's world map W_s = frame_s ∘ D_s, applied to the calibrated model at new poses
    W = {}
    for s in ("a", "b"):
        R, t = (v.numpy() for v in rigid_xyz(torch.tensor(rep["stations"][s], dtype=DTYPE)))
        Rf, tf = np.asarray(fr["stations"][s]["R"]), np.asarray(fr["stations"][s]["t"])
        W[s] = (Rf @ R, Rf @ t + tf)
    q_new = np.vstack([T.sample_poses(100, np.random.default_rng(6)),
                       T.sample_poses(100, np.random.default_rng(7), region="side")])
    qn = torch.as_tensor(np.radians(q_new), dtype=DTYPE)
    with torch.no_grad():
        p_cal = fk(qn, g).numpy()
        p_tool = {s: fk(qn, {**g, "tool": g["tool"] + torch.tensor(rep["station_tools"][s], dtype=DTYPE)}).numpy()
                  for s in ("a", "b")}                  # the model with each station's marker
    assert np.linalg.norm(rep["station_tools"]["b"]) == pytest.approx(np.linalg.norm(dtool), abs=1e-3)
    for s, twin in (("a", a), ("b", b)):
        truth = twin.to_tracker(twin.expected_position(q_new))
        assert np.linalg.norm(rigid(*W[s], p_tool[s]) - truth, axis=1).max() < 0.05, s
    # the gauge H (calibrated base -> twin base) from station a; station b must then be T_b ∘ H
    H_R, H_t = a.R.T @ W["a"][0], a.R.T @ (W["a"][1] - a.t)
    Rb, tb = b.R @ H_R, b.R @ H_t + b.t
    assert np.degrees(Rotation.from_matrix(W["b"][0].T @ Rb).magnitude()) < 0.001
    assert np.linalg.norm(rigid(*W["b"], p_cal) - rigid(Rb, tb, p_cal), axis=1).max() < 0.05
    # the campaigns are split on their own (8:1:1, seed 7) and carried through every table
    pts = aligned(pd.read_parquet("data/interim/points.parquet").merge(
        pd.read_parquet("data/interim/split.parquet"), on="point_id"), cal,
        theory_geometry(load_robot(params["robot"]), fr["tool_mm"]))
    assert pts[CAMPAIGN].unique().tolist() == ["front", "side"] and pts[STATION].unique().tolist() == ["a", "b"]
    assert pts.point_id.str.startswith("side:B").sum() == 150
    counts = read_json("reports/split.json")["per_campaign"]
    assert counts["side"] == {**{k: len(v) for k, v in split_indices(150, [0.8, 0.1, 0.1], 7).items()},
                              "holdout": 0}
    side = pts[pts[CAMPAIGN] == "side"]
    expected = np.empty(150, object)
    for name, rows in split_indices(150, [0.8, 0.1, 0.1], 7).items():
        expected[rows] = name
    assert side.split.tolist() == expected.tolist()
    assert set(rep["campaigns"]) == {"front", "side"}
    assert rep["campaigns"]["side"]["test"]["calibrated"]["mean_mm"] < 0.02
    # aligned: station b's measured points in station a's base frame, where the model lives
    with torch.no_grad():
        model = fk(torch.as_tensor(np.radians(side[JOINTS_DEG].to_numpy()), dtype=DTYPE), g).numpy()
    assert np.linalg.norm(side[MEAS].to_numpy() - model, axis=1).max() < 0.02


def test_a_campaign_name_that_is_a_path_is_refused_before_anything_is_written(tmp_path, monkeypatch):
    """A review (2026-12-06): `campaigns.more: {'../evil': ...}` made `ingest campaign ../evil` write
    data/interim/evil.parquet and reports/evil.json outside campaigns/ (`../ingest` would have replaced the
    ingest stage's own outputs); `x/y` failed after reading, on a folder that does not exist."""
    monkeypatch.chdir(tmp_path)
    files = {"joints": str(ROOT / "data/raw/station_b/joints.csv"), "tracker": str(ROOT / "data/raw/station_b/tracker.csv")}
    for name in ("../evil", "../ingest", "x/y", "a:b", ".hidden", ""):
        p = json.loads(json.dumps(PARAMS))
        p["campaigns"]["more"] = {name: {"ingest": files, "station": "s2"}}
        with pytest.raises(ValueError, match=r"campaigns.more: campaign name .*: letters, digits, _ and -"):
            ingest.run_campaign(p, name)
        assert not any(tmp_path.rglob("*")), list(tmp_path.rglob("*"))
    p["campaigns"]["more"] = {"station_b-2": {"ingest": files, "station": "s2"}}
    ingest.run_campaign(p, "station_b-2")
    assert (tmp_path / "data/interim/campaigns/station_b-2.parquet").is_file()


def test_an_inherited_setting_that_does_not_fit_a_campaign_is_named_where_it_is_overridden(tmp_path, monkeypatch):
    """A review (2026-12-06): a campaigns.more campaign inherits the ingest section's settings; where one did
    not fit its file, the error named `ingest.<key>`, and following it broke the main campaign. It now names
    the campaign's own key (campaigns.more.b.ingest.<key>), as validate.campaigns' do."""
    monkeypatch.chdir(tmp_path)
    for f in ("joints", "tracker"):                                 # station b's export with ';' and decimal commas
        text = (ROOT / f"data/raw/station_b/{f}.csv").read_text()
        Path(f"b_{f}.csv").write_text(text.replace(",", ";").replace(".", ","))
    p = json.loads(json.dumps(PARAMS))
    p["ingest"]["sep"] = ","                                        # the main campaign's, inherited
    p["campaigns"]["more"] = {"b": {"ingest": {"joints": "b_joints.csv", "tracker": "b_tracker.csv"}, "station": "s2"}}
    with pytest.raises(ValueError) as e:
        ingest.run_campaign(p, "b")
    assert "campaigns.more.b.ingest.sep" in str(e.value) and not re.search(r"(?<!\.)\bingest\.sep", str(e.value)), e.value
    p["campaigns"]["more"]["b"]["ingest"]["sep"] = ";"                 # where it says: read
    assert ingest.run_campaign(p, "b")["n_kept"] == 300


def test_more_campaigns_are_checked_with_the_params_key(tmp_path, monkeypatch):
    p = json.loads(json.dumps(PARAMS))
    p["campaigns"]["more"] = {"b": {"ingest": {"joints": "x.csv"}, "station": "s2"}}
    with pytest.raises(ValueError, match=r"campaigns.more.b.ingest: needs tracker"):
        ingest.run_campaign(p, "b")
    p["campaigns"]["more"] = {"main": {"ingest": {"joints": "x.csv", "tracker": "x.csv"}, "station": "s2"}}
    with pytest.raises(ValueError, match=r"campaigns.more.main: the name of the ingest section's campaign"):
        ingest.run(p)
    p["campaigns"]["more"] = {"b": {"ingest": {"joints": "x.csv", "tracker": "x.csv"}, "station": "s2",
                                    "frame": "same"}}
    with pytest.raises(ValueError, match=r"campaigns.more.b: unknown key\(s\) \['frame'\]"):
        ingest.run(p)
    for override, key in (({"target_residual_mm": 0}, "target_residual_mm: a distance > 0 mm, got 0"),
                          ({"orientation": {"sequence": "XYW"}}, "orientation.sequence: "),
                          ({"sep": "|"}, "sep: auto, ',', ';' or tab, got '|'"),
                          ({"colums": {}}, "unknown key(s) ['colums']"),
                          ({"orientation": "euler"}, "orientation: expected a mapping"),
                          ({"columns": None}, "columns: expected a mapping")):
        # review (2026-11-29): named params.yaml ingest.<key>, whose own value was valid
        p["campaigns"]["more"] = {"b": {"ingest": {"joints": "x.csv", "tracker": "x.csv", **override},
                                        "station": "s2"}}
        with pytest.raises(ValueError) as e:
            ingest.run_campaign(p, "b")
        sep = ": " if key.startswith("unknown") else "."
        assert f"params.yaml campaigns.more.b.ingest{sep}{key}" in str(e.value), str(e.value)
    p["campaigns"]["more"] = {"b": {"ingest": {"joints": "x.csv", "tracker": "x.csv"}, "station": "s2"}}
    monkeypatch.chdir(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"campaign 'b' .* is not ingested"):
        ingest.run({**merged_params("twin-2stations", PARAMS), "campaigns": p["campaigns"],
                    "ingest": {**PARAMS["ingest"], "joints": str(ROOT / "data/raw/joints.csv"),
                               "tracker": str(ROOT / "data/raw/tracker.csv")}})


def test_a_stations_points_are_turned_into_the_first_ones_frame_orientations_too():
    """A mutation review: the measured orientations of a further station turned by R, not Rᵀ, passed. Station b
    turned 30° about z and 10 mm along x: its point and its probe's orientation back in the first's frame."""
    g = nominal_geometry(T.ur5())
    R_b = Rotation.from_euler("z", 30, degrees=True)
    R_meas = Rotation.from_euler("xyz", [10, -20, 40], degrees=True)
    p = np.array([400.0, -100.0, 300.0])
    df = pd.DataFrame([{STATION: "b", **dict(zip(JOINTS_DEG, [0.0] * 6)), **dict(zip(MEAS, R_b.apply(p) + [10, 0, 0])),
                        **dict(zip(THEORY, p)), **dict(zip(ERR, [0.0] * 3)),
                        **dict(zip(MEAS_Q, (R_b * R_meas).as_quat(scalar_first=True)))}])
    out = aligned(df, Calibration(g, {"b": [0, 0, np.radians(30), 10.0, 0, 0]}), g)
    np.testing.assert_allclose(out[MEAS].to_numpy()[0], p, atol=1e-9)
    back = Rotation.from_quat(out[MEAS_Q].to_numpy()[0], scalar_first=True)
    assert (back.inv() * R_meas).magnitude() < 1e-12


def test_a_warmer_arm_is_longer_by_its_expansion():
    """A mutation review: d left unexpanded passed. 10 K warmer at 23e-6/K: every a and d 1.00023 times."""
    g = nominal_geometry(T.ur5())
    warm = at_temperature(g, 10.0, 23e-6)
    for k in ("a", "d"):
        np.testing.assert_allclose(warm[k].numpy(), g[k].numpy() * 1.00023, rtol=1e-12)
    assert warm["d"][0].item() == pytest.approx(89.159 * 1.00023)        # UR5's d1, 89.159 mm
    assert torch.equal(warm["alpha"], g["alpha"])

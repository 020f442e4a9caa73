"""The digital twin: reproducible data, physics sanity, noise floor, difficulty."""
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from pipeline.lib.project.columns import JOINTS_DEG
from pipeline.lib.project.config import load_params
from pipeline.lib.robot.kinematics import DTYPE, fk, fk_numpy, link_frames
from pipeline.lib.sim import twin as T
from pipeline.lib.sim.difficulty import difficulty
from pipeline.lib.sim.twin_files import generate

ROOT = Path(__file__).resolve().parents[1]
RAW = ROOT / "data" / "raw"


@pytest.fixture(scope="module")
def twin():
    return T.Twin(T.SEED)


@pytest.fixture(scope="module")
def recorded():
    return json.loads((RAW / "twin.json").read_text())


def test_committed_files_are_what_the_generator_makes(tmp_path, recorded):
    rec = generate(tmp_path, T.SEED, params=None)         # no difficulty: fast
    for name in ("joints.csv", "tracker.csv", "validation/joints.csv", "validation/tracker.csv"):
        assert (tmp_path / name).read_bytes() == (RAW / name).read_bytes(), name
    fresh = json.loads((tmp_path / "twin.json").read_text())
    assert {k: v for k, v in recorded.items() if k != "difficulty"} == fresh
    assert rec["seed"] == recorded["seed"] == T.SEED


def test_twin_from_json_is_the_generator_twin(twin):
    again = T.Twin.from_json(RAW / "twin.json")
    q = twin.poses(50)
    np.testing.assert_allclose(again.expected_position(q), twin.expected_position(q), atol=1e-8)
    np.testing.assert_allclose(again.to_tracker(q[:, :3]), twin.to_tracker(q[:, :3]), atol=1e-8)
    assert again.noise_floor_mm == pytest.approx(twin.noise_floor_mm, abs=1e-6)


def test_files_follow_the_data_contract():
    j, t = pd.read_csv(RAW / "joints.csv"), pd.read_csv(RAW / "tracker.csv")
    assert list(j.columns) == ["point_id"] + [f"j{i}_deg" for i in range(1, 7)]
    assert list(t.columns) == ["Name", "X", "Y", "Z", "QW", "QX", "QY", "QZ"]       # the probe orientation: a 6-DoF tracker
    assert len(j) == len(t) == 724 and (j["point_id"] == t["Name"]).all()
    assert j["point_id"].iloc[0] == "P0001" and j["point_id"].is_unique
    line = (RAW / "joints.csv").read_text().splitlines()[1]
    assert all(len(v.split(".")[1]) == 6 for v in line.split(",")[1:])
    line = (RAW / "tracker.csv").read_text().splitlines()[1]
    cells = line.split(",")[1:]
    assert all(len(v.split(".")[1]) == 4 for v in cells[:3]) and all(len(v.split(".")[1]) == 10 for v in cells[3:])
    q = np.array(cells[3:], float)                                           # a unit quaternion, scalar first
    assert abs(np.linalg.norm(q) - 1) < 1e-9 and q[0] >= 0
    # frontal workspace: flange in front of the robot, above the table; robot ≈3 m from the tracker
    p = fk_numpy(j.iloc[:, 1:].to_numpy(), T.ur5())
    assert (p[:, 0] < 0).all() and (p[:, 2] > 0).all()
    assert 2500 < np.linalg.norm(t[["X", "Y", "Z"]].to_numpy().mean(0)) < 3500


def test_perfect_twin_is_nominal_fk(twin):
    perfect = T.Twin(errors=T.zero_errors())
    q = twin.poses(50)
    np.testing.assert_allclose(perfect.expected_position(q), fk_numpy(q, T.ur5()), atol=1e-9)
    np.testing.assert_allclose(perfect.actual_joints(q), q, atol=1e-12)


def test_errors_have_the_stated_size(twin):
    e = twin.errors
    assert 0.07 <= np.abs(e["d_mm"]).min() and np.abs(e["a_mm"]).max() <= 0.35
    assert np.abs(e["beta_deg"][[1, 2]]).min() > 0 and not e["beta_deg"][[0, 3, 4, 5]].any()
    q = twin.poses()
    dq = twin.actual_joints(q) - q                              # compliance + gear error
    assert 0.02 < np.abs(dq[:, 1]).max() < 0.5                  # shoulder sags by a tenth of a degree
    # gravity torques from the true chain: shoulder carries the whole arm (tens of N·m)
    tau = T.gravity_torques(torch.as_tensor(np.radians(q), dtype=DTYPE), twin.geometry)
    assert 20 < tau[:, 1].abs().max() < 80 and tau[:, 0].abs().max() < 1e-9


def test_gravity_torque_of_a_stretched_arm():
    """Arm stretched horizontally (q2 = 0): shoulder torque = sum m_k g (lever arm)."""
    g = T.true_geometry(T.zero_errors())
    q = torch.zeros(1, 6, dtype=DTYPE)
    tau = T.gravity_torques(q, g)[0].numpy()
    F = link_frames(q, g)[0].numpy()
    com = np.einsum("kij,kj->ki", F[1:, :3, :3], T.LINK_COM) + F[1:, :3, 3]
    lever = com[1:, 0] - F[1, 0, 3]                             # x offsets from the shoulder
    expected = (T.LINK_MASS[1:] * 9.80665 * lever).sum() / 1000.0
    assert abs(abs(tau[1]) - abs(expected)) < 1e-9 and abs(tau[1]) > 30


def test_drive_averages_to_the_expected_position(twin):
    q = np.repeat(twin.poses(4), 4000, axis=0)
    meas = twin.drive(q, np.random.default_rng(0)).reshape(4, 4000, 3).mean(1)
    target = twin.to_tracker(twin.expected_position(q[::4000]))
    assert np.abs(meas - target).max() < 0.004                  # 5 sigma of the mean


def test_noise_floor(twin, recorded):
    assert recorded["noise_floor_mm"] == pytest.approx(twin.noise_floor_mm, abs=1e-6)
    q = twin.poses(300)
    # tracker noise alone: analytic E|N(0, s^2 I3)| = 1.5958 s
    quiet = T.Twin(errors={**twin.errors, "joint_sigma_deg": 0.0})
    assert quiet.noise_floor(q) == pytest.approx(1.5958 * T.TRACKER_SIGMA_MM, rel=0.01)
    # with repeatability: between sqrt(2/pi) and 1 times sqrt(trace of the covariance)
    qt = torch.as_tensor(np.radians(twin.actual_joints(q)), dtype=DTYPE)
    J = torch.func.vmap(torch.func.jacrev(lambda x: fk(x[None], twin.geometry)[0]))(qt)
    s_j = np.radians(T.JOINT_SIGMA_DEG)
    rms = np.sqrt(3 * T.TRACKER_SIGMA_MM ** 2 + s_j ** 2 * (J ** 2).sum((1, 2)).numpy())
    floor = twin.noise_floor(q)
    assert np.sqrt(2 / np.pi) * rms.mean() < floor < rms.mean()
    assert 0.04 < floor < 0.08


def test_difficulty_is_that_of_a_real_ur5(twin, recorded):
    params = load_params(ROOT / "params.yaml")
    j, t = pd.read_csv(RAW / "joints.csv"), pd.read_csv(RAW / "tracker.csv")
    d = difficulty(j, t, params, twin)
    rec = recorded["difficulty"]
    assert d["frame_outliers"] == sorted(recorded["misreads"]) == rec["frame_outliers"]
    assert d["nominal_after_frame_mean_mm"] == pytest.approx(rec["nominal_after_frame_mean_mm"], abs=1e-6)
    for s in ("train", "val", "test"):
        assert d["classical_fit_mean_mm"][s] == pytest.approx(rec["classical_fit_mean_mm"][s], abs=1e-4)
        assert d["rigid_fit_mean_mm"][s] == pytest.approx(rec["rigid_fit_mean_mm"][s], abs=1e-4)
    assert 0.9 < d["nominal_after_frame_mean_mm"] < 1.3           # real UR5: ≈1 mm
    assert 0.15 < d["rigid_fit_mean_mm"]["test"] < 0.35           # rigid DH: the sag remains
    assert d["rigid_fit_mean_mm"]["test"] > 3 * recorded["noise_floor_mm"]
    # elasto-geometric: the sag is explained, the gear error and the joints' fine structure are not
    # (well above the floor still: what the per-joint error maps are for)
    assert 2 * recorded["noise_floor_mm"] < d["classical_fit_mean_mm"]["test"] < 0.6 * d["rigid_fit_mean_mm"]["test"]


def test_validation_campaign_is_the_same_arm_from_another_tracker_pose(twin, recorded):
    """Half the validation poses in the default campaign's region, half at the side (joint 1 at
    70-150°, never visited by the default campaign); measured from another tracker pose."""
    v = recorded["validation"]
    j = pd.read_csv(RAW / "validation" / "joints.csv")
    t = pd.read_csv(RAW / "validation" / "tracker.csv")
    assert len(j) == len(t) == sum(v["n"].values()) == 300 and (j.point_id == t.Name).all()
    front, side = j.j1_deg[:150], j.j1_deg[150:]
    default = pd.read_csv(RAW / "joints.csv").j1_deg
    assert front.between(default.min() - 1, default.max() + 1).all()
    assert side.min() > default.max() + 10
    R = np.asarray(v["tracker_pose"]["R"])
    assert np.degrees(np.arccos((np.trace(R.T @ twin.R) - 1) / 2)) > 10     # the tracker moved
    moved = T.Twin(twin.seed, twin.errors, (R, np.asarray(v["tracker_pose"]["t"])))
    q = j[JOINTS_DEG].to_numpy()
    expected = moved.to_tracker(moved.expected_position(q))
    assert np.linalg.norm(t[["X", "Y", "Z"]].to_numpy() - expected, axis=1).mean() < 0.1   # noise only


def test_a_further_campaign_never_redraws_the_training_campaign():
    """Review D: validation_campaign's seed is absolute (725); a twin whose own seed is 725 drew its
    'independent' campaign from its training streams: 150 of 300 validation poses were training poses.
    Now a further campaign with the twin's own seed is refused."""
    t = T.Twin(T.VALIDATION["seed"])
    with pytest.raises(ValueError, match="seed 725 is the twin's own"):
        t.validation_campaign(T.VALIDATION["seed"], {"front": 5}, "V")


def test_another_seed_is_another_arm_tracker_and_poses(twin):
    """A mutation review: the twin's errors, its tracker's pose and its poses drawn from the default seed
    whatever the seed passed every test (each checked only at seed 724). Another seed: another arm (its marker
    elsewhere at the same joints), another tracker pose, other poses; the same seed again, the same twin."""
    other, again = T.Twin(T.SEED + 1), T.Twin(T.SEED + 1)
    q = twin.poses(50)
    assert np.abs(other.expected_position(q) - twin.expected_position(q)).max() > 0.01
    assert np.abs(other.t - twin.t).max() > 1.0 and not np.allclose(other.R, twin.R)
    assert not np.allclose(other.poses(10), twin.poses(10))
    assert np.array_equal(again.poses(10), other.poses(10)) and np.array_equal(again.expected_position(q),
                                                                               other.expected_position(q))


def test_the_drive_check_measures_through_the_noise_and_a_tcp_turns_with_the_probe(twin):
    """A mutation review: the drive check's "after" measured noise-free (flattering any compensation) and a TCP
    moved with the probe unturned passed every test that needs no trained project. Driven to the angles whose
    noise-free landing is the target, the twin shows its noise floor (a perfect compensation, within 15%); a TCP
    150 mm along the probe's z, its noise-free pose the target, lands within the noise too."""
    from pipeline.lib.sim.drive import drive_check, tcp_drive_check
    frame = {"R": twin.R.tolist(), "t": twin.t.tolist()}
    q = twin.poses(2000)
    summary, err = drive_check(twin, frame, np.random.default_rng(1), q, q, twin.expected_position(q))
    assert summary["after"]["3d"]["mean"] == pytest.approx(twin.noise_floor_mm, rel=0.15)
    o = np.array([0.0, 0.0, 150.0])
    p, R = twin.expected_pose(q)
    summary, err = tcp_drive_check(twin, frame, np.random.default_rng(1), np.random.default_rng(2), q, q,
                                   p + R @ o, o)
    assert twin.noise_floor_mm < summary["after"]["3d"]["mean"] < 2 * twin.noise_floor_mm


def test_each_committed_twin_campaign_is_recognised_by_its_files_and_a_changed_one_is_not(recorded, tmp_path):
    """A mutation review: the validation campaign left out of the twin's record of what it made passed (the drive
    check and twin-side judgement then skipped as for a real robot's campaign)."""
    from pipeline.lib.reading.campaigns import made_by_twin, pair_sha256
    for name, folder in (("main", RAW), ("validation", RAW / "validation"), ("station_b", RAW / "station_b")):
        assert made_by_twin(recorded, pair_sha256(folder / "joints.csv", folder / "tracker.csv")) == name
    edited = tmp_path / "tracker.csv"
    edited.write_bytes((RAW / "validation/tracker.csv").read_bytes().replace(b"\n", b"\n ", 1))
    assert made_by_twin(recorded, pair_sha256(RAW / "validation/joints.csv", edited)) is None

"""Digital twin: a virtual UR5 that is as wrong as a real one, and the default campaign.

The twin's true arm differs from the nominal UR5 table (docs/method.md stage 3) the
way real arms do:
  geometric      DH length errors (d, a), twist errors (alpha), joint zero
                 offsets, parallel-axis tilts (beta, joints 2-3), and a marker
                 offset on the flange (the pipeline's nominal tool is 0);
  non-geometric  gravity-driven joint compliance (torque of the link masses at
                 their centres of mass about each joint axis, computed on the
                 true chain, divided by a joint stiffness), periodic gear
                 error (1 and 2 cycles per revolution of each joint) and a fine
                 angular structure per joint (FINE: a few components of 18-72
                 cycles per revolution, features of 5-20°, tens of arcseconds,
                 as the IPA UR10 shows; issue 22);
  wrist          errors only the probe's orientation reveals (WRIST, issue 34): a tilt of joint 6's
                 axis (an Ry tilt after joint 5), a joint-6 angle map (a few low harmonics of tens
                 of arcsec) and the probe's rotation on the flange; its own stream, not tuned to
                 flatter a model;
  measurement    joint repeatability noise, tracker noise (position and, as a 6-DoF probe such
                 as the T-Mac measures it, orientation), a few gross tracker misreads, and an
                 unknown tracker pose ≈3 m from the robot.
Everything derives from one seed (SEED), through named random streams, so a
change in one part (say, the poses) does not reshuffle the others.

API
    twin = Twin(seed=SEED)              # or Twin(errors=zero_errors()) for a perfect arm
    twin = Twin.from_json("data/raw/twin.json")   # the twin a campaign was made with
    twin.actual_joints(q_deg)           # (n, 6) joint angles the arm really takes (deg)
    twin.expected_position(q_deg)       # (n, 3) base-frame marker position, noise-free
    twin.to_tracker(p_base)             # (n, 3) base -> tracker frame, P = R Q + t (eq. 20)
    twin.drive(q_deg, rng)              # (n, 3) one tracker measurement per pose (noisy, no misreads)
    twin.drive_pose(q_deg, rng, orng)   # the same and the probe's measured orientation (n, 3, 3)
    twin.expected_pose(q_deg)           # (n, 3), (n, 3, 3) base-frame marker and probe orientation, noise-free
    twin.noise_floor_mm                 # 3D MAE a perfect model still shows (Monte Carlo)
    twin.campaign(n=724)                # (joints_df, tracker_df, misreads {id: offset mm}),
                                        # the tables in docs/data-format.md format
    twin.validation_campaign()          # a second campaign: tracker moved, poses front and side
    twin.validation_campaign(726, {"side": 300}, "B")   # the same from a second station, side only

`python -m pipeline.commands.twin` (lib/sim/twin_files.py generate) writes data/raw/{joints.csv, tracker.csv, twin.json},
data/raw/validation/{joints.csv, tracker.csv} and data/raw/station_b/ (the second
station's training campaign, preset twin-2stations): twin.json holds the seed, the true
errors, the noise floor, the misread ids, the validation campaign's tracker pose and
the measured difficulty (nominal DH after the frame fit; classical calibration).
"""
from functools import cached_property
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from scipy.spatial.transform import Rotation

from pipeline.lib.project.columns import JOINTS_DEG
from pipeline.lib.project.config import read_json
from pipeline.lib.robot.frames import quaternions
from pipeline.lib.robot.kinematics import DTYPE, TOOL_ROT, fk, fk_pose, gravity_torques, nominal_geometry
from pipeline.lib.robot.poses import RULES, acceptable
from pipeline.lib.robot.robots import nominal_robot


SEED = 724
RAW = Path("data/raw")
N_POINTS = 724
N_MISREADS = 5

# The true arm's link masses (kg; the last includes the marker mount) and centres of
# mass in each link's own DH frame (mm): Universal Robots' published table (robots.py),
# rounded, as a real arm differs from its datasheet.
LINK_MASS = np.array([3.7, 8.4, 2.3, 1.2, 1.2, 0.25])
LINK_COM = np.array([[0.0, -25.61, 1.93], [212.5, 0.0, 113.36], [150.0, 0.0, 26.5],
                     [0.0, -1.8, 16.34], [0.0, 1.8, 16.34], [0.0, 0.0, -1.159]])

# Magnitudes, tuned so that the campaign is as hard as a real UR5 (measured into
# twin.json): nominal DH is ≈1.1 mm off after the frame fit, and a rigid DH
# calibration still leaves ≈0.24 mm (test split) of non-geometric error; an
# elasto-geometric one (joint compliance under gravity) explains the sag and leaves
# the gear error, ≈0.075 mm, above the noise floor (≈0.056 mm).
# Each geometric parameter is drawn as sign * U(lo, hi) from the "errors" stream.
RANGES = {
    "d_mm": (0.07, 0.35), "a_mm": (0.07, 0.35),
    "alpha_deg": (0.015, 0.07), "offset_deg": (0.015, 0.07), "beta_deg": (0.015, 0.055),
    "gear_amp_deg": (0.005, 0.02),             # per joint and harmonic (1, 2 cycles/rev)
}
TILT_JOINTS = (2, 3)                           # 1-based: the parallel axes
# Marker offset in the flange frame, each component scaled by U(0.8, 1.2). Sub-mm:
# the tracker software defines the flange centre from a scan of the flange and
# target tool (paper sec. 3.1), so only a residual offset remains. With the wrist
# turned over the whole sphere, |tool| mm of offset costs ≈|tool| mm of nominal
# error after the frame fit, so a few mm would swamp everything else.
TOOL_MM = np.array([0.15, -0.2, 0.45])
# Effective joint stiffness (gear and link flexibility lumped), scaled by U(0.8, 1.2):
# the shoulder sags ≈0.2° under the arm's own weight when stretched.
STIFFNESS_NM_PER_RAD = np.array([1.0e4, 1.0e4, 5.0e3, 1.3e3, 1.3e3, 1.3e3])
# The factory set the joint zeros under gravity, in this pose: deflections are
# relative to it, tau(q) - tau(q_zero) (a constant part would be a zero offset).
ZERO_POSE_DEG = [0.0, -65.0, 95.0, -110.0, 0.0, 0.0]
JOINT_SIGMA_DEG = 0.002                        # repeatability, per joint (1 sigma)
TRACKER_SIGMA_MM = 0.03                        # tracker noise, per axis (1 sigma)
MISREAD_MM = (5.0, 40.0)                       # size of a gross misread
TRACKER_DISTANCE_MM = (2800.0, 3200.0)         # robot base to tracker origin
MEAN_NORM_3D = 2.0 * np.sqrt(2.0 / np.pi)      # E|x| for x ~ N(0, I_3): 1.5958

# Regions of the workspace: joint 1 sampling range and flange azimuth window (deg, from -x).
# The default campaign covers the front; the validation campaign adds the side (joint 1 at
# 70-150°, which the default campaign never visits).
REGIONS = {"front": ((-60.0, 60.0), (-60.0, 60.0)), "side": ((70.0, 150.0), (-150.0, -80.0))}
# The validation campaign: the same arm another day, the tracker moved (its own tracker pose,
# from this seed's streams), half the poses in the front (inside the default campaign's
# coverage), half at the side (outside it). No misreads: a validation campaign is cleaned.
VALIDATION = {"seed": 725, "n": {"front": 150, "side": 150}, "dir": "validation", "prefix": "V"}
# A second training campaign from a second tracker station (the twin-2stations preset): its poses
# at the side, so this campaign covers joint space the default one never visits, as Series_B does
# on the real UR10. Cleaned, like the validation campaign. The tracker's pose is drawn at random
# (sample_tracker_pose), not placed to see those poses: the twin has no line of sight, and by
# plan.rules.tracker_side_deg the station would not see them (docs/planning.md).
STATION_B = {"seed": 726, "n": {"side": 300}, "dir": "station_b", "prefix": "B"}

# The fine angular structure of each joint (issue 22: the IPA UR10 carries per-joint errors with
# features of 5-20° and single components of 40-60″; the gtpn UR5 shows none). Per joint,
# `components` sinusoids in the joint's angle with an integer number of cycles per revolution
# (a transmission's errors repeat every turn) and amplitudes in arcsec, from their own stream
# ("fine"), so the other errors, poses and noise are the same draws as without it.
FINE = {"components": 3, "cycles": (18, 72), "amp_arcsec": (10.0, 40.0)}

# The wrist (issue 34): what a marker on joint 6's axis cannot see. A tilt of joint 6's axis (Ry after joint 5's
# DH transform, as the parallel axes' beta), a joint-6 angle error of a few low harmonics (a worn or eccentric
# last gear), the probe's rotation on the flange (a mount is never square), and the 6-DoF probe's orientation
# noise (per axis, 1 sigma; a T-Mac reads about 0.01° = 36″). From their own streams ("wrist", "orientation"),
# so every other draw is as before.
WRIST = {"beta5_deg": (0.02, 0.06), "j6_components": 3, "j6_cycles": (2, 8), "j6_amp_arcsec": (30.0, 90.0),
         "tool_rot_deg": (0.1, 0.5), "orientation_sigma_arcsec": 20.0}
ORIENTATION_COLUMNS = ["QW", "QX", "QY", "QZ"]   # the tracker export's probe orientation (scalar first)

STREAMS = {"errors": 1, "tracker": 2, "poses": 3, "noise": 4, "misreads": 5, "floor": 6, "fine": 7, "wrist": 8,
           "orientation": 9}


def stream(seed: int, name: str) -> np.random.Generator:
    """Independent random stream `name` of the master seed."""
    return np.random.default_rng(np.random.SeedSequence([seed, STREAMS[name]]))


def ur5():
    return nominal_robot("ur5")


# ----------------------------------------------------------------------------- errors

def sample_errors(seed: int = SEED) -> dict:
    """The twin's true deviations from nominal (numpy, readable units)."""
    rng = stream(seed, "errors")
    signed = lambda lo_hi, n: rng.choice([-1.0, 1.0], n) * rng.uniform(*lo_hi, n)
    beta = np.zeros(6)
    beta[[j - 1 for j in TILT_JOINTS]] = signed(RANGES["beta_deg"], len(TILT_JOINTS))
    return {
        "d_mm": signed(RANGES["d_mm"], 6),
        "a_mm": signed(RANGES["a_mm"], 6),
        "alpha_deg": signed(RANGES["alpha_deg"], 6),
        "offset_deg": signed(RANGES["offset_deg"], 6),
        "beta_deg": beta,
        "tool_mm": TOOL_MM * rng.uniform(0.8, 1.2, 3),
        "stiffness_Nm_per_rad": STIFFNESS_NM_PER_RAD * rng.uniform(0.8, 1.2, 6),
        "gear_amp_deg": rng.uniform(*RANGES["gear_amp_deg"], (6, 2)),   # harmonics 1, 2 per rev
        "gear_phase_rad": rng.uniform(0.0, 2 * np.pi, (6, 2)),
        "joint_sigma_deg": JOINT_SIGMA_DEG,
        "tracker_sigma_mm": TRACKER_SIGMA_MM,
        **sample_fine(seed),
        **sample_wrist(seed),
    }


def sample_wrist(seed: int = SEED) -> dict:
    """The wrist's errors (WRIST), from the "wrist" stream."""
    rng = stream(seed, "wrist")
    sign = lambda n: rng.choice([-1.0, 1.0], n)
    k = WRIST["j6_components"]
    return {"wrist_beta5_deg": float(sign(1)[0] * rng.uniform(*WRIST["beta5_deg"])),
            "j6_cycles": rng.integers(WRIST["j6_cycles"][0], WRIST["j6_cycles"][1] + 1, k).astype(float),
            "j6_amp_arcsec": rng.uniform(*WRIST["j6_amp_arcsec"], k),
            "j6_phase_rad": rng.uniform(0.0, 2 * np.pi, k),
            "tool_rot_deg": sign(3) * rng.uniform(*WRIST["tool_rot_deg"], 3),
            "orientation_sigma_arcsec": WRIST["orientation_sigma_arcsec"]}


def sample_fine(seed: int = SEED) -> dict:
    """The joints' fine angular structure (FINE), from the "fine" stream."""
    rng = stream(seed, "fine")
    shape = (6, FINE["components"])
    return {"fine_cycles": rng.integers(FINE["cycles"][0], FINE["cycles"][1] + 1, shape).astype(float),
            "fine_amp_arcsec": rng.uniform(*FINE["amp_arcsec"], shape),
            "fine_phase_rad": rng.uniform(0.0, 2 * np.pi, shape)}


def zero_errors() -> dict:
    """A perfect arm and instrument: nominal geometry, rigid, no gear error, no noise."""
    e = {k: np.zeros_like(v) for k, v in sample_errors(0).items()
         if isinstance(v, np.ndarray)}
    e["stiffness_Nm_per_rad"] = np.full(6, np.inf)
    return {**e, "joint_sigma_deg": 0.0, "tracker_sigma_mm": 0.0, "wrist_beta5_deg": 0.0,
            "orientation_sigma_arcsec": 0.0}


def true_geometry(errors: dict, robot=None) -> dict:
    """Nominal geometry (default UR5) plus the geometric errors (kinematics geometry dict), the true
    link masses (the UR5's: LINK_MASS, LINK_COM; another arm's: its robots.py table); rigid (the twin
    applies its joint compliance itself, relative to its zero pose)."""
    robot = robot or ur5()
    g = nominal_geometry(robot)
    t = lambda v: torch.as_tensor(np.asarray(v, float), dtype=DTYPE)
    mass, com = (LINK_MASS, LINK_COM) if robot.name == "ur5" else (robot.mass, robot.com)
    beta = np.radians(errors["beta_deg"]) + np.radians([0, 0, 0, 0, errors.get("wrist_beta5_deg", 0.0), 0])
    return {**g,
            "d": g["d"] + t(errors["d_mm"]), "a": g["a"] + t(errors["a_mm"]),
            "alpha": g["alpha"] + t(np.radians(errors["alpha_deg"])),
            "offset": g["offset"] + t(np.radians(errors["offset_deg"])),
            "beta": g["beta"] + t(beta),
            "tool": g["tool"] + t(errors["tool_mm"]), "mass": t(mass), "com": t(com),
            TOOL_ROT: t(np.radians(errors.get("tool_rot_deg", np.zeros(3))))}


def sample_tracker_pose(seed: int = SEED) -> tuple[np.ndarray, np.ndarray]:
    """Unknown tracker pose: any rotation, robot base ≈3 m from the tracker origin."""
    rng = stream(seed, "tracker")
    R = Rotation.random(random_state=rng).as_matrix()
    direction = rng.normal(size=3)
    t = direction / np.linalg.norm(direction) * rng.uniform(*TRACKER_DISTANCE_MM)
    return R, t


# ----------------------------------------------------------------------------- physics

def gear_error_rad(q: np.ndarray, amp_deg: np.ndarray, phase: np.ndarray, cycles=(1.0, 2.0)) -> np.ndarray:
    """Periodic transmission error of each joint: sum over its components of A sin(h q + phi), rad;
    q (..., 6) rad, amp_deg and phase (6, k), cycles per revolution h (k,) or (6, k)."""
    return np.radians((amp_deg * np.sin(q[..., None] * np.asarray(cycles, float) + phase)).sum(-1))


# ----------------------------------------------------------------------------- poses

def sample_poses(n: int, rng: np.random.Generator, robot=None, region: str = "front") -> np.ndarray:
    """n commanded poses (deg, 6 decimals) spread over a region of the workspace (REGIONS).

    Rejection sampling from wide joint ranges; a pose is kept when (nominal FK, the rules of
    poses.RULES, lib/robot/poses.py): the flange is in the region (front: azimuth within ±60° of -x; side:
    -150..-80°), 300-850 mm from the base axis, 0-750 mm above the table), the elbow is up and above
    the wrist, every wrist frame clears the table (z > 40 mm) and the base column
    (> 180 mm from the axis), and the elbow (|sin q3| > 0.15) and wrist
    (|sin q5| > 0.2) stay away from their singularities.
    """
    g = nominal_geometry(robot or ur5())
    j1, azimuth = REGIONS[region]
    lo = np.array([j1[0], -160.0, -160.0, -270.0, -160.0, -180.0])
    hi = np.array([j1[1], -20.0, 160.0, 90.0, 160.0, 180.0])
    out = []
    while sum(len(o) for o in out) < n:
        q = np.round(rng.uniform(lo, hi, (4 * n, 6)), 6)
        out.append(q[_acceptable(q, g, azimuth)])
    return np.concatenate(out)[:n]


def _acceptable(q_deg: np.ndarray, g: dict, azimuth_deg: tuple) -> np.ndarray:
    """The twin's rules (poses.RULES) in the azimuth window of a region."""
    return acceptable(q_deg, g, RULES, azimuth_deg=azimuth_deg)


# ----------------------------------------------------------------------------- twin

class Twin:
    """A virtual UR5 (or `robot`: another catalogue arm) with true geometric and non-geometric errors
    and a tracker."""

    def __init__(self, seed: int = SEED, errors: dict | None = None,
                 tracker_pose: tuple | None = None, robot: str = "ur5"):
        self.seed = seed
        self.robot = nominal_robot(robot)               # the arm's nominal table (the demo fleet: ur10 too)
        self.errors = sample_errors(seed) if errors is None else errors
        self.R, self.t = sample_tracker_pose(seed) if tracker_pose is None else tracker_pose
        self.geometry = true_geometry(self.errors, self.robot)
        self.compliance = 1.0 / np.asarray(self.errors["stiffness_Nm_per_rad"], float)  # rad/(N·m)
        q_ref = torch.as_tensor(np.radians([ZERO_POSE_DEG]), dtype=DTYPE)
        with torch.no_grad():      # the joint zeros were set under gravity, in this pose
            self.tau_ref = gravity_torques(q_ref, self.geometry).numpy()[0]

    @classmethod
    def from_json(cls, path) -> "Twin":
        """The twin recorded in a twin.json (its errors and tracker pose, as written)."""
        rec = read_json(path)
        errors = {k: np.asarray(v, float) if isinstance(v, list) else float(v)
                  for k, v in rec["errors"].items()}
        pose = np.asarray(rec["tracker_pose"]["R"]), np.asarray(rec["tracker_pose"]["t"])
        twin = cls(rec["seed"], errors, pose)
        if "noise_floor_mm" in rec:
            twin.__dict__["noise_floor_mm"] = rec["noise_floor_mm"]    # fills the cached_property
        return twin

    def actual_joints(self, q_deg) -> np.ndarray:
        """Joint angles (deg) the arm really takes when commanded q_deg: gear error + compliance."""
        q = np.radians(np.asarray(q_deg, float))
        q = q + gear_error_rad(q, self.errors["gear_amp_deg"], self.errors["gear_phase_rad"])
        if "fine_amp_arcsec" in self.errors:         # a twin.json from before issue 22 has none
            q = q + gear_error_rad(q, np.asarray(self.errors["fine_amp_arcsec"]) / 3600.0,
                                   self.errors["fine_phase_rad"], self.errors["fine_cycles"])
        if "j6_amp_arcsec" in self.errors:           # ... nor one from before issue 34 a wrist
            j6 = np.radians((np.asarray(self.errors["j6_amp_arcsec"]) / 3600.0
                             * np.sin(q[..., 5:6] * self.errors["j6_cycles"] + self.errors["j6_phase_rad"])).sum(-1))
            q = q + np.stack([np.zeros_like(j6)] * 5 + [j6], -1)
        with torch.no_grad():
            tau = gravity_torques(torch.as_tensor(q, dtype=DTYPE), self.geometry).numpy()
        return np.degrees(q + (tau - self.tau_ref) * self.compliance)  # joint gives way to torque

    def _fk(self, q_deg: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return fk(torch.as_tensor(np.radians(q_deg), dtype=DTYPE), self.geometry).numpy()

    def expected_position(self, q_deg) -> np.ndarray:
        """Noise-free base-frame marker position (mm) for commanded q_deg (n, 6)."""
        return self._fk(self.actual_joints(q_deg))

    def _pose(self, q_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with torch.no_grad():
            p, R = fk_pose(torch.as_tensor(np.radians(q_deg), dtype=DTYPE), self.geometry)
        return p.numpy(), R.numpy()

    def expected_pose(self, q_deg) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free base-frame marker position (n, 3) mm and probe orientation (n, 3, 3) for commanded q_deg."""
        return self._pose(self.actual_joints(q_deg))

    def drive_pose(self, q_deg, rng: np.random.Generator, orng: np.random.Generator):
        """Command q_deg (n, 6) once: the tracker's reading of the marker (n, 3), as `drive` (the same draws
        from rng), and of the probe's orientation (n, 3, 3), its noise from orng."""
        q = self.actual_joints(q_deg)
        q = q + rng.normal(0.0, self.errors["joint_sigma_deg"], q.shape)
        p, R = self._pose(q)
        p = self.to_tracker(p) + rng.normal(0.0, self.errors["tracker_sigma_mm"], p.shape)
        sigma = np.radians(self.errors.get("orientation_sigma_arcsec", 0.0) / 3600.0)
        noise = Rotation.from_rotvec(orng.normal(0.0, sigma, (len(q), 3))).as_matrix()
        return p, noise @ self.R @ R

    def to_tracker(self, p_base) -> np.ndarray:
        """Base frame -> tracker frame: P = R Q + t (eq. 20)."""
        return np.asarray(p_base, float) @ self.R.T + self.t

    def drive(self, q_deg, rng: np.random.Generator) -> np.ndarray:
        """Command q_deg (n, 6) once; the tracker's reading (n, 3) of where the marker lands."""
        q = self.actual_joints(q_deg)
        q = q + rng.normal(0.0, self.errors["joint_sigma_deg"], q.shape)
        p = self.to_tracker(self._fk(q))
        return p + rng.normal(0.0, self.errors["tracker_sigma_mm"], p.shape)

    def poses(self, n: int = N_POINTS, seed: int | None = None, region: str = "front") -> np.ndarray:
        """The campaign's commanded poses (deg)."""
        return sample_poses(n, stream(self.seed if seed is None else seed, "poses"), self.robot, region=region)

    def noise_floor(self, q_deg, repeats: int = 64, seed: int | None = None) -> float:
        """Monte Carlo mean |measured - expected| (mm) over poses q_deg and repeated drives."""
        rng = stream(self.seed if seed is None else seed, "floor")
        expected = self.to_tracker(self.expected_position(q_deg))
        q = np.repeat(np.asarray(q_deg, float), repeats, axis=0)
        err = self.drive(q, rng) - np.repeat(expected, repeats, axis=0)
        return float(np.linalg.norm(err, axis=1).mean())

    @cached_property
    def noise_floor_mm(self) -> float:
        """The 3D MAE a perfect model would still show on the campaign's poses."""
        return self.noise_floor(self.poses())

    def campaign(self, n: int = N_POINTS, seed: int | None = None):
        """(joints_df, tracker_df, misreads) in the docs/data-format.md format; misreads: {id: offset mm}."""
        seed = self.seed if seed is None else seed
        q = self.poses(n, seed)
        ids = [f"P{i + 1:04d}" for i in range(n)]
        P, R = self.drive_pose(q, stream(seed, "noise"), stream(seed, "orientation"))
        rng = stream(seed, "misreads")
        misreads = {}
        for i in sorted(rng.choice(n, min(N_MISREADS, n), replace=False)):
            u = rng.normal(size=3)
            off = u / np.linalg.norm(u) * rng.uniform(*MISREAD_MM)
            P[i] += off
            misreads[ids[i]] = off
        joints = pd.DataFrame(q, columns=JOINTS_DEG)
        joints.insert(0, "point_id", ids)
        return joints, tracker_table(ids, P, R), misreads


    def validation_campaign(self, seed: int = VALIDATION["seed"], n: dict = VALIDATION["n"],
                            prefix: str = VALIDATION["prefix"]):
        """A further campaign of this arm (joints_df, tracker_df, tracker pose (R, t)): the tracker at
        another pose (from `seed`), n[region] poses per region, ids V0001..; measured without misreads.
        `seed` must differ from the twin's own: its streams would redraw the training campaign's poses and
        noise (the same "poses" and "noise" streams), an independent campaign holding training poses."""
        if seed == self.seed:
            raise ValueError(f"twin: a further campaign's seed {seed} is the twin's own (its training campaign's "
                             "poses and noise would be drawn again); use another seed")
        R, t = sample_tracker_pose(seed)
        moved = Twin(self.seed, self.errors, (R, t))
        rng = stream(seed, "poses")
        q = np.concatenate([sample_poses(k, rng, region=r) for r, k in n.items()])
        ids = [f"{prefix}{i + 1:04d}" for i in range(len(q))]
        joints = pd.DataFrame(q, columns=JOINTS_DEG)
        joints.insert(0, "point_id", ids)
        return joints, tracker_table(ids, *moved.drive_pose(q, stream(seed, "noise"), stream(seed, "orientation"))), (R, t)


def tracker_table(ids: list, P: np.ndarray, R: np.ndarray) -> pd.DataFrame:
    """The tracker export: Name, X, Y, Z (mm) and the probe's orientation as a unit quaternion QW..QZ
    (scalar first), the latter as text of 10 decimals (1e-10: far below the noise; the positions are
    written with 4)."""
    out = pd.DataFrame(P, columns=["X", "Y", "Z"])
    out.insert(0, "Name", ids)
    for c, v in zip(ORIENTATION_COLUMNS, quaternions(R).T):
        out[c] = [f"{x:.10f}" for x in v]
    return out

"""Robot models as data: the one source of every DH table and joint limit.

Standard DH (paper eq. 1, docs/method.md stage 3), per joint i:
    T_i = Rz(theta_i + offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i)
Lengths in mm, angles in rad. The physics branch, the twin, calibration and
compensation all build their chains from `load_robot(params["robot"])`.
"""
from dataclasses import dataclass, field

import numpy as np

from .config import check_keys

PI2 = np.pi / 2

# CB3 nominal tables (docs/method.md). Joint limits are the controller's software
# limits (±360° on every UR joint). Link masses (kg) and centres of mass (mm, in
# each link's own DH frame) after Universal Robots' "Parameters for calculations
# of kinematics and dynamics": the gravity torques of the elasto-geometric
# calibration (kinematics.gravity_torques) are computed from them. Joint torque
# (N·m) and speed (rad/s) limits after the UR datasheets, for the exported URDF.
UR_JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
             "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]     # as the UR controller names them
UR_LINKS = ["shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link"]
TABLES = {
    "ur5": dict(
        d=[89.159, 0.0, 0.0, 109.15, 94.65, 82.3],
        a=[0.0, -425.0, -392.25, 0.0, 0.0, 0.0],
        alpha=[PI2, 0.0, 0.0, PI2, -PI2, 0.0],
        limits_deg=[[-360.0, 360.0]] * 6,
        mass=[3.7, 8.393, 2.33, 1.219, 1.219, 0.1879],
        com=[[0.0, -25.61, 1.93], [212.5, 0.0, 113.36], [150.0, 0.0, 26.5],
             [0.0, -1.8, 16.34], [0.0, 1.8, 16.34], [0.0, 0.0, -1.159]],
        effort_nm=[150.0, 150.0, 150.0, 28.0, 28.0, 28.0],
        velocity_rad_s=[3.15] * 6,
    ),
    "ur10": dict(
        d=[127.3, 0.0, 0.0, 163.941, 115.7, 92.2],
        a=[0.0, -612.0, -572.3, 0.0, 0.0, 0.0],
        alpha=[PI2, 0.0, 0.0, PI2, -PI2, 0.0],
        limits_deg=[[-360.0, 360.0]] * 6,
        mass=[7.1, 12.7, 4.27, 2.0, 2.0, 0.365],
        com=[[21.0, 0.0, 27.0], [380.0, 0.0, 158.0], [240.0, 0.0, 68.0],
             [0.0, 7.0, 18.0], [0.0, 7.0, 18.0], [0.0, 0.0, -26.0]],
        effort_nm=[330.0, 330.0, 150.0, 56.0, 56.0, 56.0],
        velocity_rad_s=[2.09, 2.09, 3.14, 3.14, 3.14, 3.14],
    ),
}


@dataclass
class Robot:
    """A six-joint arm: nominal standard-DH table, joint limits, link masses, tool (marker) offset."""
    name: str
    d: np.ndarray                 # (6,) mm
    a: np.ndarray                 # (6,) mm
    alpha: np.ndarray             # (6,) rad
    offset: np.ndarray            # (6,) rad, joint zero offsets
    limits_deg: np.ndarray        # (6, 2) min, max
    mass: np.ndarray              # (6,) kg per link (custom: 0, no gravity torques)
    com: np.ndarray               # (6, 3) mm, each link's centre of mass in its DH frame
    effort_nm: np.ndarray         # (6,) joint torque limits (custom: 0, unknown)
    velocity_rad_s: np.ndarray    # (6,) joint speed limits (custom: 0, unknown)
    tool: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) mm, in the flange frame

    @property
    def joint_names(self) -> list[str]:
        return UR_JOINTS if self.name in TABLES else [f"joint_{i}" for i in range(1, 7)]

    @property
    def link_names(self) -> list[str]:
        return UR_LINKS if self.name in TABLES else [f"link_{i}" for i in range(1, 7)]

    @property
    def reach(self) -> float:
        """Rough reach (mm): sum of link lengths, for sanity checks on scale."""
        return float(np.abs(self.a).sum() + np.abs(self.d).sum())

    def check_joints(self, q_deg: np.ndarray) -> np.ndarray:
        """Bool mask (n, 6): True where a joint angle lies outside its limits."""
        lo, hi = self.limits_deg[:, 0], self.limits_deg[:, 1]
        return (q_deg < lo) | (q_deg > hi)


def load_robot(cfg: dict) -> Robot:
    """Build a Robot from the `robot:` section of params.yaml.

    cfg = {"model": "ur5" | "ur10" | "custom",
           "dh": {"d": [...], "a": [...], "alpha_deg": [...], "offset_deg": [...]}  (custom only),
           "joint_limits_deg": [[lo, hi]] * 6 or null,
           "tool_mm": [x, y, z]}
    """
    check_keys(cfg, "robot")
    name = cfg["model"]
    if name == "custom":
        dh = cfg["dh"] or {}
        missing = [k for k in ("d", "a", "alpha_deg", "offset_deg") if k not in dh]
        if missing:
            raise ValueError(f"params.yaml robot.dh: custom robot needs {missing} "
                             f"(keys d, a, alpha_deg, offset_deg)")
        table = dict(d=dh["d"], a=dh["a"], alpha=np.radians(dh["alpha_deg"]),
                     offset=np.radians(dh["offset_deg"]), limits_deg=[[-360.0, 360.0]] * 6,
                     mass=[0.0] * 6, com=[[0.0] * 3] * 6, effort_nm=[0.0] * 6, velocity_rad_s=[0.0] * 6)
    elif name in TABLES:
        table = dict(TABLES[name], offset=[0.0] * 6)
    else:
        raise ValueError(f"params.yaml robot.model: unknown robot {name!r}; "
                         f"use one of {sorted(TABLES)} or 'custom'")
    if cfg["joint_limits_deg"] is not None:
        table["limits_deg"] = cfg["joint_limits_deg"]
    arr = {k: np.asarray(v, dtype=float) for k, v in table.items()}
    for k in ("d", "a", "alpha", "offset", "mass"):
        if arr[k].shape != (6,):
            raise ValueError(f"params.yaml robot: {k} must have 6 entries, got {arr[k].shape}")
    if arr["limits_deg"].shape != (6, 2):
        raise ValueError("params.yaml robot.joint_limits_deg must be 6 pairs [min, max]")
    tool = np.asarray(cfg["tool_mm"], dtype=float)
    if tool.shape != (3,):
        raise ValueError("params.yaml robot.tool_mm must be [x, y, z] in mm")
    return Robot(name=name, tool=tool, **arr)


def nominal_robot(name: str) -> Robot:
    """A catalogue robot (TABLES) with its own limits and no tool."""
    return load_robot({"model": name, "dh": None, "joint_limits_deg": None, "tool_mm": [0.0, 0.0, 0.0]})

"""Robot models as data: the one source of every DH table and joint limit.

Standard DH (paper eq. 1, docs/method.md stage 3), per joint i:
    T_i = Rz(theta_i + offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i)
Lengths in mm, angles in rad. The physics branch, the twin, calibration and
compensation all build their chains from `load_robot(params["robot"])`. A custom
arm's table may be given in modified DH (Craig); it is converted to standard DH
on loading (modified_to_standard).
"""
from dataclasses import dataclass, field

import numpy as np

from pipeline.lib.project.config import OFFSET_MM_MAX, check_keys, real

PI2 = np.pi / 2

# Universal Robots' nominal tables (docs/method.md). d, a, alpha, link masses (kg) and
# centres of mass (mm, in each link's own DH frame) after Universal Robots' "DH parameters
# for calculations of kinematics and dynamics"
# (universal-robots.com/articles/ur/application-installation/dh-parameters-for-calculations-of-kinematics-and-dynamics),
# cross-checked against UniversalRobots/Universal_Robots_ROS2_Description, config/<model>/
# default_kinematics.yaml and physical_parameters.yaml: the gravity torques of the elasto-geometric
# calibration (kinematics.gravity_torques) are computed from them. Joint limits are the controller's
# software limits (±360° on every UR joint). Joint torque (N·m) and speed (rad/s) limits after the UR
# user manuals and datasheets (that repository's joint_limits.yaml), for the exported URDF.
UR_JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
             "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]     # as the UR controller names them
UR_LINKS = ["shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link"]
UR_ALPHA = [PI2, 0.0, 0.0, PI2, -PI2, 0.0]
UR_LIMITS = [[-360.0, 360.0]] * 6   # UR3, UR3e: wrist 3 turns without limit; ±360° is the range the pipeline plans in


LIMIT_SLACK_DEG = 1e-9      # a limit of 1.5° clamped in radians reads 1.5000000000000002° back: within it


def rad_s(*deg_s: float) -> list[float]:
    """Joint speed limits, °/s -> rad/s."""
    return np.radians(deg_s).tolist()


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
        velocity_rad_s=rad_s(180, 180, 180, 180, 180, 180),
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
        velocity_rad_s=rad_s(120, 120, 180, 180, 180, 180),
    ),
    "ur3": dict(
        d=[151.9, 0.0, 0.0, 112.35, 85.35, 81.9],
        a=[0.0, -243.65, -213.25, 0.0, 0.0, 0.0],
        alpha=UR_ALPHA, limits_deg=UR_LIMITS,
        mass=[2.0, 3.42, 1.26, 0.8, 0.8, 0.35],
        com=[[0.0, -20.0, 0.0], [130.0, 0.0, 115.7], [50.0, 0.0, 23.8],
             [0.0, 0.0, 10.0], [0.0, 0.0, 10.0], [0.0, 0.0, -20.0]],
        effort_nm=[56.0, 56.0, 28.0, 12.0, 12.0, 12.0],
        velocity_rad_s=rad_s(180, 180, 180, 360, 360, 360),
    ),
    "ur3e": dict(
        d=[151.85, 0.0, 0.0, 131.05, 85.35, 92.1],
        a=[0.0, -243.55, -213.2, 0.0, 0.0, 0.0],
        alpha=UR_ALPHA, limits_deg=UR_LIMITS,
        mass=[1.98, 3.4445, 1.437, 0.871, 0.805, 0.261],
        com=[[0.0, -20.0, 0.0], [130.0, 0.0, 115.7], [50.0, 0.0, 23.8],
             [0.0, 0.0, 10.0], [0.0, 0.0, 10.0], [0.0, 0.0, -20.0]],
        effort_nm=[54.0, 54.0, 28.0, 9.0, 9.0, 9.0],
        velocity_rad_s=rad_s(180, 180, 180, 360, 360, 360),
    ),
    "ur5e": dict(
        d=[162.5, 0.0, 0.0, 133.3, 99.7, 99.6],
        a=[0.0, -425.0, -392.2, 0.0, 0.0, 0.0],
        alpha=UR_ALPHA, limits_deg=UR_LIMITS,
        mass=[3.761, 8.058, 2.846, 1.37, 1.3, 0.365],
        com=[[0.0, -25.61, 1.93], [212.5, 0.0, 113.36], [150.0, 0.0, 26.5],
             [0.0, -1.8, 16.34], [0.0, 1.8, 16.34], [0.0, 0.0, -1.159]],
        effort_nm=[150.0, 150.0, 150.0, 28.0, 28.0, 28.0],
        velocity_rad_s=rad_s(180, 180, 180, 180, 180, 180),
    ),
    "ur10e": dict(
        d=[180.7, 0.0, 0.0, 174.15, 119.85, 116.55],
        a=[0.0, -612.7, -571.55, 0.0, 0.0, 0.0],
        alpha=UR_ALPHA, limits_deg=UR_LIMITS,
        mass=[7.369, 13.051, 3.989, 2.1, 1.98, 0.615],
        com=[[21.0, 0.0, 27.0], [380.0, 0.0, 158.0], [240.0, 0.0, 68.0],
             [0.0, 7.0, 18.0], [0.0, 7.0, 18.0], [0.0, 0.0, -26.0]],
        effort_nm=[330.0, 330.0, 150.0, 54.0, 54.0, 54.0],
        velocity_rad_s=rad_s(120, 120, 180, 180, 180, 180),
    ),
    "ur16e": dict(
        d=[180.7, 0.0, 0.0, 174.15, 119.85, 116.55],
        a=[0.0, -478.4, -360.0, 0.0, 0.0, 0.0],
        alpha=UR_ALPHA, limits_deg=UR_LIMITS,
        mass=[7.369, 10.45, 4.321, 2.18, 2.033, 0.907],
        com=[[0.0, -16.0, 30.0], [302.0, 0.0, 160.0], [194.0, 0.0, 65.0],
             [0.0, -9.0, 11.0], [0.0, 18.0, 12.0], [0.0, 0.0, -44.0]],
        effort_nm=[330.0, 330.0, 150.0, 54.0, 54.0, 54.0],
        velocity_rad_s=rad_s(120, 120, 180, 180, 180, 180),
    ),
    "ur20": dict(
        d=[236.3, 0.0, 0.0, 201.0, 159.3, 154.3],
        a=[0.0, -862.0, -728.7, 0.0, 0.0, 0.0],
        alpha=UR_ALPHA, limits_deg=UR_LIMITS,   # the elbow too: the ROS 2 description's ±180° is a planning limit
        # link 6: UR's page; the ROS 2 description has 0.926 kg at [0, 0, -29.3] (the UR30's)
        mass=[16.343, 29.632, 7.879, 3.054, 3.126, 0.846],
        com=[[0.0, -61.0, 6.2], [522.6, 0.0, 209.8], [323.4, 0.0, 60.4],
             [0.0, -2.6, 39.3], [0.0, 2.4, 37.9], [0.0, -0.3, -31.8]],
        effort_nm=[738.0, 738.0, 433.0, 107.0, 107.0, 107.0],
        velocity_rad_s=rad_s(120, 120, 150, 210, 210, 210),
    ),
    "ur30": dict(
        d=[236.3, 0.0, 0.0, 201.0, 159.3, 154.3],
        a=[0.0, -637.0, -503.7, 0.0, 0.0, 0.0],
        alpha=UR_ALPHA, limits_deg=UR_LIMITS,
        mass=[16.343, 28.542, 7.156, 3.054, 3.126, 0.926],
        com=[[-0.1, -60.0, 6.9], [389.4, 0.0, 210.3], [225.7, 0.0, 62.9],
             [0.0, -4.8, 35.3], [0.0, 4.6, 34.1], [0.0, 0.0, -29.3]],
        # torque and speed limits: the UR20's (the ROS 2 description's source is the UR20 manual)
        effort_nm=[738.0, 738.0, 433.0, 107.0, 107.0, 107.0],
        velocity_rad_s=rad_s(120, 120, 150, 210, 210, 210),
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
        """Bool mask (n, 6): True where a joint angle lies outside its limits (or is NaN: not within them), by
        more than LIMIT_SLACK_DEG: a solver's answer clamped at a limit in radians is at it, in degrees too."""
        lo, hi = self.limits_deg[:, 0] - LIMIT_SLACK_DEG, self.limits_deg[:, 1] + LIMIT_SLACK_DEG
        return ~((q_deg >= lo) & (q_deg <= hi))

    def check_joint_speed(self, vel_rad_s: float, key: str) -> None:
        """A script's movej speed (rad/s: its leading joint's, which may be any joint) no faster than this
        robot's slowest joint; else, or where the limits are unknown (a custom robot without
        robot.dh.velocity_deg_s), a ValueError naming the setting key."""
        if not (self.velocity_rad_s > 0).all():
            raise ValueError(f"params.yaml {key}: the robot's joint speed limits are unknown (a custom robot), so a "
                             "movej speed cannot be checked: set robot.dh.velocity_deg_s. Nothing written")
        low = float(np.min(self.velocity_rad_s))
        if vel_rad_s > low:
            raise ValueError(f"params.yaml {key}: {vel_rad_s:g} rad/s, faster than the {self.name}'s slowest joint "
                             f"({low:.4g} rad/s, {np.degrees(low):.0f} deg/s), which may lead the move: a slip of "
                             "unit? Nothing written")


DH_KEYS = ("d", "a", "alpha_deg", "offset_deg")
JOINT_LIMIT_KEYS = ("velocity_deg_s", "effort_nm")     # a custom robot's datasheet joint limits (optional)
CONVENTIONS = ("standard", "modified")


def modified_to_standard(d, a, alpha, offset) -> dict:
    """A modified-DH table (Craig: T_i = Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i + offset_i) Tz(d_i),
    row i holding a_{i-1}, alpha_{i-1}) as the standard-DH table of the same chain.

    Rx and Tx commute, so the product regroups as Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i) with a_i,
    alpha_i from row i + 1, and a_6 = alpha_6 = 0 (the modified frame 6 is the flange). Row 1's
    a_0, alpha_0 are a fixed transform before joint 1, which the nominal chain has no place for:
    they must be 0.
    """
    a, alpha = np.asarray(a, dtype=float), np.asarray(alpha, dtype=float)
    if a.shape != (6,) or alpha.shape != (6,):
        raise ValueError("params.yaml robot.dh: a and alpha_deg must have 6 entries")
    if a[0] != 0.0 or alpha[0] != 0.0:
        raise ValueError(
            f"params.yaml robot.dh: with convention: modified, the first row's a (a_0 = {a[0]:g} mm) and "
            f"alpha_deg (alpha_0 = {np.degrees(alpha[0]):g}°) must be 0: they are a fixed transform before "
            f"joint 1, which the nominal chain does not carry (its base frame is joint 1's). Set both to 0: "
            f"the frame stage's base-to-tracker fit takes up that transform")
    return dict(d=d, a=np.append(a[1:], 0.0), alpha=np.append(alpha[1:], 0.0), offset=offset)


def finite(v, shape: tuple, bound: float = np.inf) -> bool:
    """v is numbers (a list, tuple or array; no text, no booleans) of this shape, all finite, each within ±bound."""
    try:
        cells = np.asarray(v, dtype=object)
    except (TypeError, ValueError):
        return False
    return cells.shape == shape and all(real(x) and abs(float(x)) <= bound for x in cells.ravel())


def check_tool(tool) -> np.ndarray:
    """robot.tool_mm as (3,) mm: 3 finite numbers, each within ±OFFSET_MM_MAX, else a ValueError naming the key."""
    if not finite(tool, (3,), OFFSET_MM_MAX):
        raise ValueError(f"params.yaml robot.tool_mm: [x, y, z], 3 finite numbers in mm (the marker in the flange "
                         f"frame), each within ±{OFFSET_MM_MAX:g}, got {tool!r}")
    return np.asarray(tool, dtype=float)


def within_limits(given, own) -> list:
    """robot.joint_limits_deg: 6 pairs [lo, hi] of finite degrees, lo < hi, within the robot's own limits
    (own (6, 2): a UR controller's ±360°), else a ValueError naming the key. A range beyond the arm's would let
    a waypoint 100 turns away reach a script as a movej)."""
    if not finite(given, (6, 2)) or not (np.asarray(given, float)[:, 0] < np.asarray(given, float)[:, 1]).all():
        raise ValueError(f"params.yaml robot.joint_limits_deg: null or 6 pairs [min, max] of finite degrees, min < max, "
                         f"got {given!r}")
    lim, own = np.asarray(given, float), np.asarray(own, float)
    off = np.flatnonzero((lim[:, 0] < own[:, 0]) | (lim[:, 1] > own[:, 1])) + 1
    if len(off):
        raise ValueError(f"params.yaml robot.joint_limits_deg: joint(s) {off.tolist()} beyond the robot's own limits "
                         f"{own[off[0] - 1].tolist()} deg; got {given!r}")
    return lim.tolist()


def load_robot(cfg: dict) -> Robot:
    """Build a Robot from the `robot:` section of params.yaml.

    cfg = {"model": one of TABLES | "custom",
           "dh": {"d": [...], "a": [...], "alpha_deg": [...], "offset_deg": [...],
                  "convention": "standard" | "modified" (optional, standard),
                  "velocity_deg_s": [6], "effort_nm": [6] (optional: 0, unknown)}  (custom only),
           "joint_limits_deg": [[lo, hi]] * 6 or null,
           "tool_mm": [x, y, z]}
    A modified-DH table is converted to the standard one here (modified_to_standard).
    """
    check_keys(cfg, "robot")
    name = cfg["model"]
    if not isinstance(name, str):
        raise ValueError(f"params.yaml robot.model: one of {sorted(TABLES)} or 'custom', got {name!r}")
    if name != "custom" and cfg["dh"] is not None:
        raise ValueError(f"params.yaml robot.dh: only with robot.model: custom (a {name} has its own table); "
                         f"set it to null, got {cfg['dh']!r}")
    if name == "custom":
        dh = cfg["dh"] or {}
        missing = [k for k in DH_KEYS if k not in dh]
        if missing:
            raise ValueError(f"params.yaml robot.dh: custom robot needs {missing} "
                             f"(keys d, a, alpha_deg, offset_deg)")
        unknown = sorted(set(dh) - {*DH_KEYS, "convention", *JOINT_LIMIT_KEYS})
        if unknown:
            raise ValueError(f"params.yaml robot.dh: unknown key(s) {unknown}; "
                             f"use {list(DH_KEYS)} and optionally convention, {', '.join(JOINT_LIMIT_KEYS)}")
        for key in JOINT_LIMIT_KEYS:
            v = dh.get(key)
            if v is not None and not (isinstance(v, list) and len(v) == 6 and all(real(x) and x > 0 for x in v)):
                raise ValueError(f"params.yaml robot.dh.{key}: 6 numbers > 0 (each joint's), got {v!r}")
        for key in DH_KEYS:
            if not finite(dh[key], (6,)):
                raise ValueError(f"params.yaml robot.dh.{key}: 6 finite numbers (each joint's), got {dh[key]!r}")
        convention = dh.get("convention", "standard")
        if convention not in CONVENTIONS:
            raise ValueError(f"params.yaml robot.dh.convention: {convention!r}; use one of {list(CONVENTIONS)}")
        dh_table = dict(d=dh["d"], a=dh["a"], alpha=np.radians(dh["alpha_deg"]), offset=np.radians(dh["offset_deg"]))
        if convention == "modified":
            dh_table = modified_to_standard(**dh_table)
        table = dict(dh_table, limits_deg=[[-360.0, 360.0]] * 6, mass=[0.0] * 6, com=[[0.0] * 3] * 6,
                     effort_nm=dh.get("effort_nm") or [0.0] * 6,                     # 0: unknown
                     velocity_rad_s=np.radians(dh.get("velocity_deg_s") or [0.0] * 6))
    elif name in TABLES:
        table = dict(TABLES[name], offset=[0.0] * 6)
    else:
        raise ValueError(f"params.yaml robot.model: unknown robot {name!r}; "
                         f"use one of {sorted(TABLES)} or 'custom'")
    if cfg["joint_limits_deg"] is not None:
        table["limits_deg"] = within_limits(cfg["joint_limits_deg"], table["limits_deg"])
    arr = {k: np.asarray(v, dtype=float) for k, v in table.items()}
    for k in ("d", "a", "alpha", "offset", "mass"):
        if arr[k].shape != (6,):
            raise ValueError(f"params.yaml robot: {k} must have 6 entries, got {arr[k].shape}")
    if arr["limits_deg"].shape != (6, 2):
        raise ValueError("params.yaml robot.joint_limits_deg must be 6 pairs [min, max]")
    return Robot(name=name, tool=check_tool(cfg["tool_mm"]), **arr)


def nominal_robot(name: str) -> Robot:
    """A catalogue robot (TABLES) with its own limits and no tool."""
    return load_robot({"model": name, "dh": None, "joint_limits_deg": None, "tool_mm": [0.0, 0.0, 0.0], "tcp": None})

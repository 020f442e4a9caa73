"""The calibrated kinematic chain in the formats robot software reads: URDF and UR's kinematics YAML.

The chain (kinematics.py) regrouped as joint origins: with B the base correction,
    base_link -> B Tz(d1) Rz(off1) -> [q1] -> Tx(a1) Rx(alpha1) Ry(beta1) Tz(d2) Rz(off2) -> [q2] -> ...
              -> [q6] -> Tx(a6) Rx(alpha6) Ry(beta6) = flange -> tool, tool_rot = tool0 (the probe's frame)
                                                                      -> each robot.tcp = tcp_<name>
Tz(d_i) and Rz(off_i) commute with joint i's rotation Rz(q_i), so each joint's
origin O_i = [Tx(a_{i-1}) Rx(alpha_{i-1}) Ry(beta_{i-1})] Tz(d_i) Rz(off_i) (O_1 = B Tz(d1) Rz(off1)),
the grouping of the UR ROS description, whose `default_kinematics.yaml` lists
exactly O_1..O_6 (as `shoulder` .. `wrist_3`) and puts tool0 on the last joint's frame.

What neither format holds: the joints' gravity sag (`compliance`), a joint-space
correction q -> kinematics.deflected(q). The exported chain is the rigid part:
at the deflected angles it gives the calibrated model's positions exactly.
Lengths in metres, angles in rad (URDF, REP 103); `rpy` is fixed-axis X, Y, Z.
"""
import hashlib
import re
import xml.etree.ElementTree as ET

import numpy as np
import torch
import yaml
from scipy.spatial.transform import Rotation

from pipeline.lib.robot.kinematics import DTYPE, TOOL_ROT, rigid_xyz, rotation_xyz
from pipeline.lib.robot.robots import Robot

UR_YAML_NAMES = ["shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3"]


def transform(R=None, p=None) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if p is not None:
        T[:3, 3] = p
    return T


def rot(axis: str, angle: float) -> np.ndarray:
    return transform(Rotation.from_euler(axis, angle).as_matrix())


def base_transform(g: dict) -> np.ndarray:
    """The base correction B (4, 4), mm: p_base = B p_chain (kinematics.fk)."""
    R, t = rigid_xyz(torch.as_tensor(g["base"], dtype=DTYPE))
    return transform(R.numpy(), t.numpy())


def joint_origins(g: dict) -> tuple[list[np.ndarray], np.ndarray]:
    """Joint origins O_1..O_6 (4, 4) and the flange's fixed transform after joint 6, lengths in mm."""
    B = base_transform(g)
    g = {k: np.asarray(torch.as_tensor(v, dtype=DTYPE)) for k, v in g.items()}
    after = [transform(p=[g["a"][i], 0, 0]) @ rot("x", g["alpha"][i]) @ rot("y", g["beta"][i]) for i in range(6)]
    origins = [(B if i == 0 else after[i - 1]) @ transform(p=[0, 0, g["d"][i]]) @ rot("z", g["offset"][i])
               for i in range(6)]
    return origins, after[5]


def xyz_rpy(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A pose (4, 4) in mm -> translation in m, URDF rpy (rad: R = Rz(yaw) Ry(pitch) Rx(roll))."""
    return T[:3, 3] / 1000.0, Rotation.from_matrix(T[:3, :3]).as_euler("xyz")


def _num(v) -> str:
    return " ".join(repr(float(x)) for x in v)          # repr: every digit (1e-6 mm wanted)


def tool_transform(g: dict) -> np.ndarray:
    """The probe's (marker's) frame in the flange frame (4, 4), mm: tool and, where measured, tool_rot."""
    R = rotation_xyz(torch.as_tensor(g[TOOL_ROT], dtype=DTYPE)).numpy() if TOOL_ROT in g else None
    return transform(R, np.asarray(torch.as_tensor(g["tool"], dtype=DTYPE)))


def tcp_transforms(tcp: dict | None) -> dict:
    """{name: (4, 4) mm}: each `robot.tcp` point's frame in the flange frame (rxyz_deg as rotation_xyz); a point
    given in the probe's frame is refused (tcp.in_flange carries it to the flange frame first)."""
    probe = [n for n, c in (tcp or {}).items() if c.get("frame", "flange") != "flange"]
    if probe:
        raise ValueError(f"robot.tcp {probe[0]}: in the probe's frame; tcp.in_flange carries it to the flange's")
    return {n: transform(Rotation.from_euler("xyz", c.get("rxyz_deg", [0, 0, 0]), degrees=True).as_matrix(),
                         c["xyz_mm"]) for n, c in (tcp or {}).items()}


def to_urdf(g: dict, robot: Robot, name: str = "calibrated", tcp: dict | None = None) -> str:
    """URDF text of the calibrated rigid chain: base_link, six revolute joints, flange, tool0 (the probe's
    frame) and a fixed link tcp_<name> on the flange for each `robot.tcp` point."""
    origins, flange = joint_origins(g)
    links = ["base_link", *robot.link_names, "flange", "tool0"]
    root = ET.Element("robot", name=f"{robot.name}_{name}")
    for link in links + [f"tcp_{n}" for n in tcp or {}]:
        ET.SubElement(root, "link", name=link)
    fixed = [tool_transform(g)]
    for i, (parent, child) in enumerate(zip(links[:-1], links[1:])):
        revolute = i < 6
        j = ET.SubElement(root, "joint", name=robot.joint_names[i] if revolute else f"{parent}-{child}",
                          type="revolute" if revolute else "fixed")
        T = origins[i] if revolute else (flange if i == 6 else fixed[0])
        xyz, rpy = xyz_rpy(T)
        ET.SubElement(j, "origin", xyz=_num(xyz), rpy=_num(rpy))
        ET.SubElement(j, "parent", link=parent)
        ET.SubElement(j, "child", link=child)
        if revolute:
            ET.SubElement(j, "axis", xyz="0 0 1")
            lo, hi = np.radians(robot.limits_deg[i])
            ET.SubElement(j, "limit", lower=repr(float(lo)), upper=repr(float(hi)),
                          effort=repr(float(robot.effort_nm[i])), velocity=repr(float(robot.velocity_rad_s[i])))
    for n, T in tcp_transforms(tcp).items():
        j = ET.SubElement(root, "joint", name=f"flange-tcp_{n}", type="fixed")
        xyz, rpy = xyz_rpy(T)
        ET.SubElement(j, "origin", xyz=_num(xyz), rpy=_num(rpy))
        ET.SubElement(j, "parent", link="flange")
        ET.SubElement(j, "child", link=f"tcp_{n}")
    ET.indent(root)
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def pose_entry(T: np.ndarray) -> dict:
    xyz, rpy = xyz_rpy(T)
    return {**dict(zip("xyz", map(float, xyz))), **dict(zip(("roll", "pitch", "yaw"), map(float, rpy)))}


def ur_kinematics(g: dict, tcp: dict | None = None) -> dict:
    """The UR ROS description's calibration (`default_kinematics.yaml` layout): O_1..O_6 as
    {x, y, z, roll, pitch, yaw} (m, rad) and `hash` (the description reads it; the UR driver compares it
    with the robot's own calibration's: here `spi_boter_` and a digest of the six entries). Holds no
    flange transform after joint 6 and no tool: tool0 there is joint 6's frame (`flange_residual` says
    what that leaves out). Beside `kinematics`, `tool_frames`: the probe (`marker`) and each `robot.tcp`
    point in joint 6's frame, the flange transform included: the six numbers, and `ur_pose`, the same
    frame as a UR controller's TCP takes it (set_tcp's p[x, y, z, rx, ry, rz]: m, a rotation vector)."""
    origins, flange = joint_origins(g)
    frames = {"marker": flange @ tool_transform(g), **{n: flange @ T for n, T in tcp_transforms(tcp).items()}}
    kinematics = {key: pose_entry(T) for key, T in zip(UR_YAML_NAMES, origins)}
    digest = hashlib.sha256(repr(sorted(kinematics.items())).encode()).hexdigest()[:16]
    return {"kinematics": {**kinematics, "hash": f"spi_boter_{digest}"},
            "tool_frames": {n: {**pose_entry(T), "ur_pose": ur_pose(T)} for n, T in frames.items()}}


# The plain scalars a YAML 1.2 core-schema reader (ROS 2's yaml-cpp, ruamel.yaml) takes as null, a bool, an
# int or a float (YAML 1.2.2, 10.3.2): PyYAML resolves by YAML 1.1 and writes 1e3, 0o17, -1e3 unquoted.
NOT_TEXT_1_2 = re.compile(r"null|Null|NULL|~|true|True|TRUE|false|False|FALSE"        # null, bool
                          r"|[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+"                         # int
                          r"|[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)([eE][-+]?[0-9]+)?"          # float
                          r"|[-+]?(\.inf|\.Inf|\.INF)|\.nan|\.NaN|\.NAN")                    # .inf, .nan


class _Yaml12Safe(yaml.SafeDumper):
    """PyYAML's safe dumper, quoting every string a YAML 1.2 reader would read as something else."""

    def represent_str(self, data):
        if NOT_TEXT_1_2.fullmatch(data):
            return self.represent_scalar("tag:yaml.org,2002:str", data, style="'")
        return super().represent_str(data)


_Yaml12Safe.add_representer(str, _Yaml12Safe.represent_str)


def ur_yaml_text(kin: dict) -> str:
    """ur_kinematics' dict as models/ur_calibration.yaml's text, read alike by YAML 1.1 and 1.2 readers: a
    robot.tcp name such as 1e3 or 0o17 quoted (a 1.2 reader took it for a number); other keys as PyYAML writes them."""
    return yaml.dump(kin, Dumper=_Yaml12Safe, sort_keys=False)


def ur_pose(T: np.ndarray) -> list[float]:
    """A 4×4 transform (mm) as a UR pose: [x, y, z] m and the rotation vector [rx, ry, rz] rad."""
    return [float(v) for v in (*T[:3, 3] / 1000.0, *Rotation.from_matrix(T[:3, :3]).as_rotvec())]


def flange_residual(g: dict) -> dict:
    """The flange transform after joint 6 that the UR YAML cannot carry: translation mm, rotation deg."""
    T = joint_origins(g)[1]
    return {"translation_mm": float(np.linalg.norm(T[:3, 3])),
            "rotation_deg": float(np.degrees(Rotation.from_matrix(T[:3, :3]).magnitude()))}

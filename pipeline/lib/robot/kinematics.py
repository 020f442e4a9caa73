"""Forward kinematics as differentiable torch code (the physics branch, eq. 1).

One pure function, `fk`, takes joint angles and a geometry (a dict of tensors)
and returns flange/marker positions. `DHChain` wraps a geometry as an
nn.Module so BoTER can carry it; calibration differentiates `fk` with respect
to the geometry, compensation with respect to the joint angles.

Geometry keys (all float64 tensors):
    d, a, alpha, offset   (6,)  standard DH, mm / rad
    beta                  (6,)  extra Ry(beta) after joint i's DH transform: the
                                parallel-axis tilt (Hayati) standard DH cannot express
    tool                  (3,)  marker offset in the flange frame, mm
    base                  (6,)  small base-frame correction [rx, ry, rz (rad), tx, ty, tz (mm)]
    compliance            (6,)  joint compliance, rad/(N·m): under the gravity torque tau_i(q)
                                of the links it carries, joint i turns by compliance_i * tau_i
                                (the elasto-geometric model; 0 = rigid)
    mass, com             (6,), (6, 3)  link masses (kg) and centres of mass (mm, link DH frame):
                                robot data (robots.py), never identified
    tool_rot              (3,)  optional: the marker's (probe's) rotation in the flange frame,
                                [rx, ry, rz] rad as rotation_xyz; present where the campaign measures
                                orientation (absent: the identity)

Every chain function first deflects the joints (`deflected`): q -> q + c * tau(q),
tau from the nominal-to-date geometry at the commanded q (the deflection is
≤0.3°, so tau at the deflected q differs by a second-order amount).
"""
import numpy as np
import torch
from torch import nn

from pipeline.lib.project.config import write_json
from pipeline.lib.robot.errormaps import MAP_KEYS, joint_errors
from pipeline.lib.robot.robots import Robot

DTYPE = torch.float64
GEOMETRY_KEYS = ("d", "a", "alpha", "offset", "beta", "tool", "base", "compliance", "mass", "com")
TOOL_ROT = "tool_rot"                   # the optional key: the probe's rotation in the flange
RIGID_KEYS = GEOMETRY_KEYS + (TOOL_ROT,)     # what a geometry may hold besides its error maps
GRAVITY = (0.0, 0.0, -9.80665)          # m/s² in the robot's base frame: the arm stands level


def nominal_geometry(robot: Robot) -> dict:
    """Geometry dict (float64 tensors) of the robot's nominal table and tool."""
    t = lambda v: torch.as_tensor(np.asarray(v, dtype=float), dtype=DTYPE)
    return {"d": t(robot.d), "a": t(robot.a), "alpha": t(robot.alpha),
            "offset": t(robot.offset), "beta": torch.zeros(6, dtype=DTYPE),
            "tool": t(robot.tool), "base": torch.zeros(6, dtype=DTYPE),
            "compliance": torch.zeros(6, dtype=DTYPE), "mass": t(robot.mass), "com": t(robot.com)}


def rotation_xyz(r: torch.Tensor) -> torch.Tensor:
    """Rotation matrix Rz(rz) Ry(ry) Rx(rx) from r = (..., 3) [rx, ry, rz] (rad) -> (..., 3, 3)."""
    cx, cy, cz = torch.cos(r).unbind(-1)
    sx, sy, sz = torch.sin(r).unbind(-1)
    return torch.stack([
        torch.stack([cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx], -1),
        torch.stack([sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx], -1),
        torch.stack([-sy, cy * sx, cy * cx], -1),
    ], -2)


def rigid_xyz(d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A small rigid correction [rx, ry, rz (rad), tx, ty, tz (mm)] (..., 6) -> R (..., 3, 3), t (..., 3)."""
    return rotation_xyz(d[..., :3]), d[..., 3:]


def cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a × b over the last axis (3): torch.linalg.cross; when exporting to ONNX, the same products as four
    gathers (a graph of 7 nodes, not the exporter's ~20)."""
    if not torch.compiler.is_exporting():
        return torch.linalg.cross(a, b, dim=-1)
    i, j = torch.tensor([1, 2, 0]), torch.tensor([2, 0, 1])
    at = lambda x, k: torch.index_select(x, -1, k)         # one Gather (x[..., k] would be three nodes)
    return at(a, i) * at(b, j) - at(a, j) * at(b, i)


def dh_matrices(q: torch.Tensor, g: dict) -> torch.Tensor:
    """Per-joint transforms T_i = Rz(q+offset) Tz(d) Tx(a) Rx(alpha) Ry(beta).

    q: (B, 6) rad -> (B, 6, 4, 4)
    """
    th = q + g["offset"]                                  # (B, 6)
    if torch.compiler.is_exporting():
        return dh_linear(th, g)
    ct, st = torch.cos(th), torch.sin(th)
    ca, sa = torch.cos(g["alpha"]), torch.sin(g["alpha"])  # (6,)
    cb, sb = torch.cos(g["beta"]), torch.sin(g["beta"])
    d, a = g["d"].expand_as(th), g["a"]
    zero, one = torch.zeros_like(th), torch.ones_like(th)
    # Rz Tz Tx Rx (closed form), then times Ry(beta): columns x, y, z of the rotation
    r00, r01, r02 = ct, -st * ca, st * sa
    r10, r11, r12 = st, ct * ca, -ct * sa
    r20, r21, r22 = zero, sa.expand_as(th), ca.expand_as(th)
    # R @ Ry(beta): new x = cb*x - sb*z, new z = sb*x + cb*z
    x0, x1, x2 = cb * r00 - sb * r02, cb * r10 - sb * r12, cb * r20 - sb * r22
    z0, z1, z2 = sb * r00 + cb * r02, sb * r10 + cb * r12, sb * r20 + cb * r22
    rows = [
        torch.stack([x0, r01, z0, a * ct], -1),
        torch.stack([x1, r11, z1, a * st], -1),
        torch.stack([x2, r21, z2, d], -1),
        torch.stack([zero, zero, zero, one], -1),
    ]
    return torch.stack(rows, -2)                           # (B, 6, 4, 4)


def dh_linear(th: torch.Tensor, g: dict) -> torch.Tensor:
    """dh_matrices for ONNX export: each T_i is linear in cos θ_i and sin θ_i, T_i = A_i cos θ_i + B_i sin θ_i
    + C_i, with A, B, C (6, 4, 4) of the geometry alone (folded to constants by the exporter): a graph of a
    few nodes, not ~50. The same entries as dh_matrices' closed form (to rounding: 1e-16 relative)."""
    ca, sa = torch.cos(g["alpha"]), torch.sin(g["alpha"])  # (6,)
    cb, sb = torch.cos(g["beta"]), torch.sin(g["beta"])
    o, i = torch.zeros_like(ca), torch.ones_like(ca)
    m = lambda *rows: torch.stack([torch.stack(r, -1) for r in rows], -2)            # (6, 4, 4)
    A = m([cb, o, sb, g["a"]], [sb * sa, ca, -cb * sa, o], [o, o, o, o], [o, o, o, o])
    B = m([-sb * sa, -ca, cb * sa, o], [cb, o, sb, g["a"]], [o, o, o, o], [o, o, o, o])
    C = m([o, o, o, o], [o, o, o, o], [-sb * ca, sa, cb * ca, g["d"]], [o, o, o, i])
    return torch.cos(th)[..., None, None] * A + torch.sin(th)[..., None, None] * B + C


def link_frames(q: torch.Tensor, g: dict) -> torch.Tensor:
    """Frames 0..6 of the rigid chain (no deflection) in the base frame: (B, 6) rad -> (B, 7, 4, 4)."""
    T = dh_matrices(q, g)
    F = [torch.eye(4, dtype=T.dtype, device=T.device).expand_as(T[:, 0])]  # (B, 4, 4)
    for i in range(6):
        F.append(F[-1] @ T[:, i])
    return torch.stack(F, 1)


def gravity_torques(q: torch.Tensor, g: dict) -> torch.Tensor:
    """Static gravity torque about each joint axis (N·m), (B, 6) rad -> (B, 6).

    tau_i = z_{i-1} · sum_{k >= i} (c_k - o_{i-1}) x f_k, with joint i turning about z of
    frame i-1, link k's centre of mass c_k carried by frame k and f_k = m_k g. With suffix
    sums over k >= i, S_i = sum c_k x f_k and F_i = sum f_k: tau_i = z_{i-1} · (S_i - o_{i-1} x F_i).
    """
    F = link_frames(q, g)                                                     # (B, 7, 4, 4)
    c = torch.einsum("bkij,kj->bki", F[:, 1:, :3, :3], g["com"]) + F[:, 1:, :3, 3]   # (B, 6, 3) mm
    # m_k g, made on the mass's device (no host tensor: a CUDA graph holds no copy from the host)
    f = torch.stack([g["mass"] * gk for gk in GRAVITY], -1).expand_as(c)        # (B, 6, 3) N
    suffix = lambda x: x.flip(1).cumsum(1).flip(1)                            # sum over k >= i
    z, o = F[:, :6, :3, 2], F[:, :6, :3, 3]                                   # (B, 6, 3) joint axes, origins
    moment = suffix(cross(c, f)) - cross(o, suffix(f))
    return (z * moment).sum(-1) / 1000.0                                      # N·mm -> N·m


def deflected(q: torch.Tensor, g: dict) -> torch.Tensor:
    """Joint angles the arm takes: q + compliance * tau(q) under its own weight, plus the joint error
    maps' δθ(q, tau) where the geometry has them (errormaps.py), (B, 6) rad."""
    tau = gravity_torques(q, g)
    out = q + g["compliance"] * tau
    return out + joint_errors(q, tau, g) if any(k in g for k in MAP_KEYS) else out


def fk_frames(q: torch.Tensor, g: dict) -> list[torch.Tensor]:
    """Cumulative frames T_1, T_1 T_2, ..., T_1..T_6: six (B, 4, 4) poses in the base frame
    (joints deflected under gravity by the geometry's compliance)."""
    T = dh_matrices(deflected(q, g), g)
    frames = [T[:, 0]]
    for i in range(1, 6):
        frames.append(frames[-1] @ T[:, i])
    return frames


def fk_poses(q: torch.Tensor, g: dict) -> torch.Tensor:
    """Flange poses in the base frame, (B, 6) rad -> (B, 4, 4) (no tool, no base correction)."""
    return fk_frames(q, g)[-1]


def flange_rotations(q: torch.Tensor, g: dict) -> torch.Tensor:
    """The flange's orientation in the (corrected) base frame: (B, 6) rad -> (B, 3, 3)."""
    return rotation_xyz(g["base"][:3]) @ fk_poses(q, g)[:, :3, :3]


def tool_rotation(g: dict) -> torch.Tensor:
    """The probe's rotation in the flange frame (3, 3): rotation_xyz(tool_rot), the identity without one."""
    if TOOL_ROT in g:
        return rotation_xyz(g[TOOL_ROT])
    return torch.eye(3, dtype=g["tool"].dtype, device=g["tool"].device)


def fk_pose(q: torch.Tensor, g: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """Marker position and the probe's orientation in the base frame, one FK pass:
    (B, 6) rad -> p (B, 3) mm, R (B, 3, 3) = R_base R_flange R_tool."""
    T = fk_poses(q, g)
    Rb = rotation_xyz(g["base"][:3])
    p = (T[:, :3, :3] @ g["tool"][..., None])[..., 0] + T[:, :3, 3]
    return p @ Rb.T + g["base"][3:], Rb @ T[:, :3, :3] @ tool_rotation(g)


def rotation_error(R: torch.Tensor, R_meas: torch.Tensor) -> torch.Tensor:
    """The small rotation (rad, base frame) from a measured orientation to a predicted one, R ≈ exp([e]) R_meas:
    e = vee of the skew part of R R_measᵀ, (B, 3, 3) x2 -> (B, 3); sin(angle) times the axis, within 2e-5
    relative of the angle below 0.5°. Differentiable (calibration's Jacobians)."""
    M = R @ R_meas.transpose(-1, -2)
    return 0.5 * torch.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1)


def fk(q: torch.Tensor, g: dict) -> torch.Tensor:
    """Marker position in the base frame (mm): (B, 6) rad -> (B, 3).

    p = R_base (R_flange tool + t_flange) + t_base
    """
    T = fk_poses(q, g)
    p = (T[:, :3, :3] @ g["tool"][..., None])[..., 0] + T[:, :3, 3]   # (B, 3); tool (3,) or one per pose (B, 3)
    Rb = rotation_xyz(g["base"][:3])
    return p @ Rb.T + g["base"][3:]


def fk_jacobian(q: torch.Tensor, g: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """Marker position and its geometric Jacobian: (B, 6) rad -> p (B, 3) mm, J = dp/dq (B, 3, 6) mm/rad.

    Joint i turns about the z axis of the frame before it (T_i starts with Rz),
    so column i is z_{i-1} x (p - o_{i-1}), with frame 0 the base; the base
    correction then rotates every column. The joint deflection's own derivative
    (compliance * dtau/dq, ≤1e-3 of the identity) is left out: solvers iterate on
    the exact position, so it only slows them by a hair. One FK pass, no autograd (whose three
    backward passes cost about five times as much at batch 1).
    """
    return marker_jacobian(fk_frames(q, g), g)


def fk_pose_jacobian(q: torch.Tensor, g: dict) -> tuple[torch.Tensor, ...]:
    """fk_jacobian's p (B, 3) and J (B, 3, 6), the flange's orientation R (B, 3, 3) (flange_rotations) and its
    angular Jacobian Jw (B, 3, 6) (angular_jacobian), all from one FK pass: the same bits as the three calls,
    at a third of their cost (a pose solver's step)."""
    frames = fk_frames(q, g)
    return (*marker_jacobian(frames, g), rotation_xyz(g["base"][:3]) @ frames[-1][:, :3, :3], axes_jacobian(frames, g))


def marker_jacobian(frames: list[torch.Tensor], g: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """fk_jacobian from the chain's frames (fk_frames)."""
    p = frames[-1][:, :3, :3] @ g["tool"] + frames[-1][:, :3, 3]           # (B, 3), before the base correction
    z = torch.stack([p.new_tensor([0.0, 0.0, 1.0]).expand_as(p)]
                    + [F[:, :3, 2] for F in frames[:-1]], 1)               # (B, 6, 3) joint axes
    o = torch.stack([torch.zeros_like(p)] + [F[:, :3, 3] for F in frames[:-1]], 1)   # (B, 6, 3) a point on each
    J = cross(z, p[:, None] - o).transpose(1, 2)                          # (B, 3, 6)
    Rb = rotation_xyz(g["base"][:3])
    return p @ Rb.T + g["base"][3:], Rb @ J


def angular_jacobian(q: torch.Tensor, g: dict) -> torch.Tensor:
    """d(the probe's orientation)/dq as angular velocities in the base frame: (B, 6) rad -> (B, 3, 6) rad/rad,
    column i the axis of joint i (z of the frame before it), rotated by the base correction; the tool's
    rotation does not enter (a rotation of the flange turns the probe with it)."""
    return axes_jacobian(fk_frames(q, g), g)


def axes_jacobian(frames: list[torch.Tensor], g: dict) -> torch.Tensor:
    """angular_jacobian from the chain's frames (fk_frames)."""
    B = frames[0].shape[0]
    z = torch.stack([frames[0].new_tensor([0.0, 0.0, 1.0]).expand(B, 3)]
                    + [F[:, :3, 2] for F in frames[:-1]], 2)               # (B, 3, 6)
    return rotation_xyz(g["base"][:3]) @ z


def fk_numpy(q_deg: np.ndarray, robot: Robot, geometry: dict | None = None) -> np.ndarray:
    """Convenience: joint angles in degrees (n, 6) -> positions (n, 3) mm, numpy in and out."""
    g = geometry if geometry is not None else nominal_geometry(robot)
    q = torch.as_tensor(np.radians(np.asarray(q_deg, dtype=float)), dtype=DTYPE)
    with torch.no_grad():
        return fk(q, g).numpy()


def geometry_keys(g: dict) -> tuple:
    """The keys of geometry g: GEOMETRY_KEYS, then tool_rot and the error maps' it has (errormaps.MAP_KEYS)."""
    return GEOMETRY_KEYS + tuple(k for k in (TOOL_ROT,) + MAP_KEYS if k in g)


class DHChain(nn.Module):
    """The physics branch: a geometry held as buffers (frozen; saved with the model's state)."""

    def __init__(self, geometry: dict):
        super().__init__()
        self.keys = geometry_keys(geometry)
        for k in self.keys:
            self.register_buffer(k, torch.as_tensor(geometry[k], dtype=DTYPE).clone())

    def geometry(self) -> dict:
        return {k: getattr(self, k) for k in self.keys}

    def forward(self, q: torch.Tensor) -> torch.Tensor:   # (B, 6) rad -> (B, 3) mm
        return fk(q, self.geometry())


def save_geometry(path, geometry: dict, meta: dict | None = None) -> None:
    """Write a geometry dict (mm / rad) as JSON lists (read back by geometry.Calibration.from_dict)."""
    write_json(path, {"geometry": {k: torch.as_tensor(geometry[k]).tolist() for k in geometry_keys(geometry)},
                      "units": "mm and rad; pipeline.lib.robot.kinematics geometry keys", **(meta or {})})

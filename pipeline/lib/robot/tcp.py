"""The tool centre points (`robot.tcp`) and the pose errors judged where a campaign measures orientation.

A TCP is a point rigidly fixed to the flange, c (mm, flange frame), or given where the tracker measured it,
in the probe's frame (`frame: probe`; `in_flange` moves it to the flange frame by the calibrated probe's pose:
the calibrated flange frame is not the drawing's, docs/robot-cell.md). The tracker measures the probe at
the marker, t (the geometry's tool) with rotation R_T (tool_rot) in the flange, so a TCP sits at
o = R_Tᵀ (c − t) in the probe's frame and its measured position follows from the probe's measured pose:
p_tcp = p_meas + R_meas o. A method predicts it the same way from its own pose: p_pred + R_pred o, with
o from the calibrated geometry for every method (one measured TCP to judge them all against).

`AtTcp` moves a model's answer from the marker to a TCP, p(q) + R(q) o (R: the physics branch's probe
orientation), with the TCP's own geometric Jacobian (the physics branch with the TCP as its tool): every
solver (lib/runtime/solvers.py), the Δθ table, the program compensator and the service then solve for the TCP.
"""
import numpy as np
import torch
from scipy.spatial.transform import Rotation
from torch import nn

from pipeline.lib.robot.identify import errors_3d, orientation_errors
from pipeline.lib.robot.kinematics import DTYPE, TOOL_ROT, DHChain, fk_pose, rotation_xyz


def in_flange(tcp: dict | None, geometry: dict) -> dict | None:
    """`robot.tcp` with every point in the flange frame of `geometry` ({xyz_mm, rxyz_deg}): one given in the
    probe's frame (`frame: probe`) carried by the geometry's tool and tool_rot, c = t + R_T x and R_T R;
    refused (ValueError) where the geometry has no tool_rot (the probe's orientation was never measured)."""
    if not tcp:
        return tcp
    t = np.asarray(geometry["tool"], float)
    out = {}
    for name, c in tcp.items():
        if c.get("frame", "flange") == "flange":
            out[name] = {k: v for k, v in c.items() if k != "frame"}
            continue
        if TOOL_ROT not in geometry:
            raise ValueError(f"robot.tcp {name}: given in the probe's frame, but the calibration has no probe "
                             "orientation (a campaign without it): give it in the flange frame")
        R_T = rotation_xyz(torch.as_tensor(geometry[TOOL_ROT], dtype=DTYPE)).numpy()
        R = R_T @ Rotation.from_euler("xyz", c.get("rxyz_deg", [0.0, 0.0, 0.0]), degrees=True).as_matrix()
        out[name] = {"xyz_mm": (t + R_T @ np.asarray(c["xyz_mm"], float)).tolist(),
                     "rxyz_deg": Rotation.from_matrix(R).as_euler("xyz", degrees=True).tolist()}
    return out


def probe_offsets(tcp: dict | None, geometry: dict) -> dict:
    """{name: o (3,)}: each `robot.tcp` point in the probe's frame, from the geometry's tool and tool_rot (a
    point given there: itself)."""
    if not tcp:
        return {}
    t = np.asarray(geometry["tool"], float)
    R_T = rotation_xyz(torch.as_tensor(geometry[TOOL_ROT], dtype=DTYPE)).numpy() if TOOL_ROT in geometry else np.eye(3)
    return {name: (np.asarray(c["xyz_mm"], float) if c.get("frame") == "probe" else
                   R_T.T @ (np.asarray(c["xyz_mm"], float) - t)) for name, c in tcp.items()}


def pose_of(q_deg: np.ndarray, geometry: dict) -> tuple[np.ndarray, np.ndarray]:
    """Marker positions (n, 3) mm and probe orientations (n, 3, 3) in the base frame under a geometry."""
    with torch.no_grad():
        p, R = fk_pose(torch.as_tensor(np.radians(q_deg), dtype=DTYPE), geometry)
    return p.numpy(), R.numpy()


def pose_errors(p: np.ndarray, R: np.ndarray, p_meas: np.ndarray, R_meas: np.ndarray, offsets: dict) -> dict:
    """The marker's error, the orientation's (arcsec) and each TCP's (mm) of predicted poses (p, R)
    against measured ones."""
    return {"marker": errors_3d(p, p_meas), "orientation": orientation_errors(R, R_meas),
            "tcp": {name: errors_3d(p + R @ o, p_meas + R_meas @ o) for name, o in offsets.items()}}


class AtTcp(nn.Module):
    """A model (BoTER, Ensemble or PhysicsOnly) answering for a TCP: o (3,) mm in the probe's frame
    (probe_offsets). forward(q) -> (p + R o, p_theory + R o); physics: the same chain with the TCP as tool."""

    def __init__(self, model, o):
        super().__init__()
        self.model = model
        g = model.physics.geometry()
        self.register_buffer("o", torch.as_tensor(np.asarray(o, float), dtype=DTYPE))
        R_T = rotation_xyz(g[TOOL_ROT]) if TOOL_ROT in g else torch.eye(3, dtype=DTYPE)
        self.physics = DHChain({**g, "tool": g["tool"] + R_T @ self.o})   # the TCP in the flange frame

    def delta(self, q):
        return self.model.delta(q)

    def forward(self, q):
        p, p_theory = self.model(q)
        arm = fk_pose(q, self.model.physics.geometry())[1] @ self.o      # (B, 3): R_probe o
        return p + arm, p_theory + arm


def at_tcp(model, tcp: dict | None, name: str, nominal: dict):
    """The model and the nominal geometry (for offline-programmed targets) moved to `robot.tcp` entry `name`:
    (AtTcp(model, o), nominal with the TCP as its tool). Refused (ValueError) for an unknown name or a model
    calibrated without orientation: its chain's orientation was never measured, so a point off the marker
    has no stated accuracy."""
    if not tcp or name not in tcp:
        raise ValueError(f"--tcp {name}: not in params.yaml robot.tcp ({', '.join(tcp or {}) or 'none set'})")
    g = model.physics.geometry()
    if TOOL_ROT not in g:
        raise ValueError(f"--tcp {name}: the model was calibrated without the probe's orientation, so a point "
                         "off the marker has no measured accuracy; calibrate on a campaign with orientation")
    return AtTcp(model, probe_offsets(tcp, g)[name]), {**nominal, "tool": torch.as_tensor(
        np.asarray(in_flange(tcp, g)[name]["xyz_mm"], float), dtype=DTYPE)}

"""Driving the twin to joint angles and measuring where it lands, in the base frame by the fitted frame:
the paper's Table 9 for the compensated angles (`drive_check`) and at a TCP (`tcp_drive_check`)."""
import numpy as np

from scipy.spatial.transform import Rotation

from pipeline.lib.learning.metrics import drive_table, stats
from pipeline.lib.robot.frames import ARCSEC, to_base
from pipeline.lib.sim.twin import Twin


def drive_check(twin: Twin, frame: dict, rng: np.random.Generator, q_before: np.ndarray,
                q_after: np.ndarray, target: np.ndarray):
    """Drive the twin to the recorded and the compensated angles (deg), measure, map to base with
    the fitted frame; returns (the paper's Table 9 stats, per-point errors (n, 6) mm)."""
    before = to_base(twin.drive(q_before, rng), frame)
    after = to_base(twin.drive(q_after, rng), frame)
    summary = {"before": drive_table(before, target), "after": drive_table(after, target),
               "noise_floor_mm": twin.noise_floor_mm}
    return summary, np.hstack([before - target, after - target])


def tcp_drive_check(twin: Twin, frame: dict, rng: np.random.Generator, orng: np.random.Generator,
                    q_before: np.ndarray, q_after: np.ndarray, target: np.ndarray, o: np.ndarray,
                    tool_rot: np.ndarray | None = None, flange_target: np.ndarray | None = None):
    """The drive check for a TCP o (3,) mm in the probe's frame: drive the twin to the recorded and the
    compensated angles, measure the probe's pose, and the TCP where it follows from it (P + R_meas o),
    in the base frame; returns (Table 9 stats before and after, per-point errors (n, 6) mm). With
    flange_target (n, 3, 3) the flange's measured orientation (R_meas tool_rotᵀ, tool_rot the model's
    probe rotation in the flange) is judged against it too: `orientation_arcsec` before and after."""
    def measured(q):
        P, R = twin.drive_pose(q, rng, orng)
        return to_base(P + R @ o, frame), np.asarray(frame["R"]).T @ R     # (n, 3), (n, 3, 3) base frame
    (before, R_before), (after, R_after) = measured(q_before), measured(q_after)
    summary = {"before": drive_table(before, target), "after": drive_table(after, target)}
    if flange_target is not None:
        def off(R):                                                          # (n,) arcsec
            return Rotation.from_matrix(R @ tool_rot.T @ flange_target.transpose(0, 2, 1)).magnitude() / ARCSEC
        summary["orientation_arcsec"] = {"before": stats(off(R_before)), "after": stats(off(R_after))}
    return summary, np.hstack([before - target, after - target])

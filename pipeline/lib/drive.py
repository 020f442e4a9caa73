"""Driving the twin to joint angles and measuring where it lands, in the base frame by the fitted frame:
the paper's Table 9 for the compensated angles (`drive_check`) and at a TCP (`tcp_drive_check`)."""
import numpy as np

from .frames import to_base
from .metrics import drive_table
from .twin import Twin


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
                    q_before: np.ndarray, q_after: np.ndarray, target: np.ndarray, o: np.ndarray):
    """The drive check for a TCP o (3,) mm in the probe's frame: drive the twin to the recorded and the
    compensated angles, measure the probe's pose, and the TCP where it follows from it (P + R_meas o),
    in the base frame; returns (Table 9 stats before and after, per-point errors (n, 6) mm)."""
    def measured(q):
        P, R = twin.drive_pose(q, rng, orng)
        return to_base(P + R @ o, frame)
    before, after = measured(q_before), measured(q_after)
    summary = {"before": drive_table(before, target), "after": drive_table(after, target)}
    return summary, np.hstack([before - target, after - target])

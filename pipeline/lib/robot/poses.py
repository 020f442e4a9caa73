"""Which joint configurations an arm may be measured in: the acceptability rules the twin samples its
campaigns by (twin.sample_poses) and the measurement planner (planning.py) chooses poses by.

A pose q (deg) passes, on the nominal chain (kinematics.link_frames: frame origins o_0..o_6, o_6 the
flange), every rule whose setting is not None (`rules`, the keys of RULES):

    radius_mm      [lo, hi]  the flange's distance from the base axis (hypot of o_6 x, y) strictly between
    height_mm      [lo, hi]  the flange's height above the base plane strictly between
    elbow_up       true      the elbow (o_2) above the wrist (o_3) ...
    elbow_min_mm   h         ... and above h
    table_mm       h         every wrist frame (o_3..o_6) above h: clear of the table the base stands on
    column_mm      r         every wrist frame farther than r from the base axis: clear of the base column
    sin_elbow      s         |sin q3| > s: away from the elbow singularity (arm stretched or folded; the turn
                             at the elbow, configuration_margin's, so a table's offsets and an offset forearm count)
    sin_wrist      s         |sin q5| > s: away from the wrist singularity (joints 4 and 6 aligned; q5 with its offset)
and, when given:
    limits_deg     (6, 2)    every joint within its limits (inclusive)
    azimuth_deg    (lo, hi)  the flange's azimuth, atan2(y, -x) in degrees, strictly between (a region)
    tracker_mm     (3,)      the marker's side: seen from the base axis, the flange's azimuth lies within
                             `tracker_side_deg` of the tracker's (no rule when the tracker stands within
                             `column_mm` of the axis, straight above or below the arm)

A move between two poses (a `movej`: every joint linear in time, all together) keeps CLEARANCE, the rules
that say where the arm may be, all along it (`moves_clear`); the others say where it may be measured.

`configuration_margin(q, geometry)` says which of the arm's eight configurations (UR's: shoulder, elbow,
wrist) a pose is in, by its signs, and how far from each singularity; `waypoints.another_configuration`
refuses an answer that left its seed's.
"""
import numpy as np
import torch

from pipeline.lib.robot.kinematics import DTYPE, link_frames

# The twin's rules (a UR5 on a table, docs/method.md): every key a planner's settings may set.
RULES = {"radius_mm": (300.0, 850.0), "height_mm": (0.0, 750.0), "elbow_up": True, "elbow_min_mm": 150.0,
         "table_mm": 40.0, "column_mm": 180.0, "sin_elbow": 0.15, "sin_wrist": 0.2, "tracker_side_deg": 90.0}
CLEARANCE = ("elbow_min_mm", "table_mm", "column_mm")     # the rules a move keeps all along it (moves_clear)
MOVE_STEP_DEG = 0.25            # a move is checked at every quarter degree of its largest joint move


def frames(q_deg: np.ndarray, geometry: dict) -> np.ndarray:
    """Frames 0..6 (n, 7, 4, 4) mm of the rigid chain `geometry` at joint angles q (n, 6) deg."""
    with torch.no_grad():
        return link_frames(torch.as_tensor(np.radians(np.asarray(q_deg, float)), dtype=DTYPE), geometry).numpy()


def origins(q_deg: np.ndarray, geometry: dict) -> np.ndarray:
    """Frame origins o_0..o_6 (n, 7, 3) mm of the rigid chain `geometry` at joint angles q (n, 6) deg."""
    return frames(q_deg, geometry)[:, :, :3, 3]


CONFIGURATION = ("shoulder", "elbow", "wrist")


def configuration_margin(q_deg: np.ndarray, geometry: dict, F: np.ndarray | None = None) -> np.ndarray:
    """How far (n, 3) a pose lies from each CONFIGURATION's singularity, signed by the side (the sine of an
    angle, in [-1, 1]): shoulder: the wrist centre o_5's bearing about the base axis, ahead of or behind joint
    2's axis (its coordinate along frame 1's x over its distance from the base axis); elbow: the turn at the
    elbow, from the upper arm (o_1 -> o_2) to the forearm (o_2 -> o_4) about joint 3's axis (a UR arm: sin q3;
    an arm whose forearm is offset, as a PUMA's: zero where it is stretched or folded, not at q3 = 0); wrist:
    sin q5 (q plus the chain's offsets). Each changes sign only through its singularity. F: the chain's
    `frames` at q, where already computed."""
    q = np.atleast_2d(np.asarray(q_deg, float))
    F = frames(q, geometry) if F is None else F                                            # (n, 7, 4, 4)
    o, z0 = F[:, :, :3, 3], F[:, 0, :3, 2]
    w = o[:, 5] - o[:, 0]
    across = np.linalg.norm(w - np.einsum("ni,ni->n", w, z0)[:, None] * z0, axis=1)      # from the base axis
    ahead = np.einsum("ni,ni->n", w, F[:, 1, :3, 0]) / np.maximum(across, 1e-9)
    upper, fore, axis = o[:, 2] - o[:, 1], o[:, 4] - o[:, 2], F[:, 2, :3, 2]
    fore = fore - np.einsum("ni,ni->n", fore, axis)[:, None] * axis                      # in the arm's plane
    elbow = np.einsum("ni,ni->n", np.cross(upper, fore), axis) / np.maximum(
        np.linalg.norm(upper, axis=1) * np.linalg.norm(fore, axis=1), 1e-9)
    theta = np.radians(q) + np.asarray(geometry["offset"], float)                          # (n, 6)
    m = np.stack([ahead, elbow, np.sin(theta[:, 4])], 1)
    return np.where(np.abs(m) < 1e-12, 0.0, m)                  # at a singularity: 0, not rounding's sign


def azimuth(p: np.ndarray) -> np.ndarray:
    """Azimuth (deg) of points (n, 3) about the base axis, measured from -x (the twin's front)."""
    return np.degrees(np.arctan2(p[..., 1], -p[..., 0]))


def checks(q_deg: np.ndarray, geometry: dict, rules: dict, limits_deg=None, azimuth_deg=None,
           tracker_mm=None) -> dict:
    """{rule: (n,) bool, True where the pose passes it} for every rule that applies (module docstring)."""
    q = np.atleast_2d(np.asarray(q_deg, float))
    F = frames(q, geometry)
    o = F[:, :, :3, 3]
    p = o[:, 6]
    r = np.hypot(p[:, 0], p[:, 1])
    out = {}
    if limits_deg is not None:
        lim = np.asarray(limits_deg, float)
        out["limits_deg"] = ((q >= lim[:, 0]) & (q <= lim[:, 1])).all(1)
    if azimuth_deg is not None:
        a = azimuth(p)
        out["azimuth_deg"] = (a > azimuth_deg[0]) & (a < azimuth_deg[1])
    if rules.get("radius_mm") is not None:
        out["radius_mm"] = (r > rules["radius_mm"][0]) & (r < rules["radius_mm"][1])
    if rules.get("height_mm") is not None:
        out["height_mm"] = (p[:, 2] > rules["height_mm"][0]) & (p[:, 2] < rules["height_mm"][1])
    if rules.get("elbow_up"):
        out["elbow_up"] = o[:, 2, 2] > o[:, 3, 2]
    if rules.get("elbow_min_mm") is not None:
        out["elbow_min_mm"] = o[:, 2, 2] > rules["elbow_min_mm"]
    if rules.get("table_mm") is not None:
        out["table_mm"] = o[:, 3:, 2].min(1) > rules["table_mm"]
    if rules.get("column_mm") is not None:
        out["column_mm"] = np.hypot(o[:, 3:, 0], o[:, 3:, 1]).min(1) > rules["column_mm"]
    if rules.get("sin_elbow") is not None or rules.get("sin_wrist") is not None:
        margin = configuration_margin(q, geometry, F)      # the chain's own angles: its offsets, an offset forearm
    if rules.get("sin_elbow") is not None:
        out["sin_elbow"] = np.abs(margin[:, 1]) > rules["sin_elbow"]
    if rules.get("sin_wrist") is not None:
        out["sin_wrist"] = np.abs(margin[:, 2]) > rules["sin_wrist"]
    if tracker_mm is not None and rules.get("tracker_side_deg") is not None:
        t = np.asarray(tracker_mm, float)
        if np.hypot(t[0], t[1]) > (rules.get("column_mm") or 0.0):
            d = (azimuth(p) - azimuth(t) + 180.0) % 360.0 - 180.0
            out["tracker_side_deg"] = np.abs(d) <= rules["tracker_side_deg"]
    return out


def acceptable(q_deg: np.ndarray, geometry: dict, rules: dict, limits_deg=None, azimuth_deg=None,
               tracker_mm=None) -> np.ndarray:
    """(n,) bool: the poses q (n, 6) deg that pass every rule that applies (`checks`)."""
    q = np.atleast_2d(np.asarray(q_deg, float))
    ok = np.ones(len(q), bool)
    for v in checks(q, geometry, rules, limits_deg, azimuth_deg, tracker_mm).values():
        ok &= v
    return ok


def moves_clear(q_from: np.ndarray, q_to: np.ndarray, geometry: dict, rules: dict,
                step_deg: float = MOVE_STEP_DEG) -> np.ndarray:
    """(m,) bool: each movej from q_from to q_to (m, 6) deg keeps the CLEARANCE rules that apply at every
    step_deg of its largest joint move, both ends included."""
    a, b = np.atleast_2d(np.asarray(q_from, float)), np.atleast_2d(np.asarray(q_to, float))
    clearance = {k: rules.get(k) for k in CLEARANCE}
    out = np.ones(len(a), bool)
    for i, (qa, qb) in enumerate(zip(a, b)):
        s = np.linspace(0.0, 1.0, max(1, int(np.ceil(np.abs(qb - qa).max() / step_deg))) + 1)[:, None]
        out[i] = acceptable(qa + s * (qb - qa), geometry, clearance).all()        # (k, 6) along the move
    return out


def rejected(q_deg: np.ndarray, geometry: dict, rules: dict, limits_deg=None, azimuth_deg=None,
             tracker_mm=None) -> list[list[str]]:
    """Per pose, the rules it fails (empty: acceptable): for messages."""
    c = checks(q_deg, geometry, rules, limits_deg, azimuth_deg, tracker_mm)
    n = len(np.atleast_2d(q_deg))
    return [[k for k, v in c.items() if not v[i]] for i in range(n)]

"""A path compensated sample by sample, checked, and the URScript that drives it (docs/robot-cell.md,
"Compensating a path"); for `python -m pipeline.commands.path`, the service's compensate_path and bench path.

    solve_sample(model, q_deg, target, cfg, robot)    the one per-sample solve (with rot: a pose)
    solve_path(model, targets, arc_mm, q_start, ...)  every sample from the previous sample's solution:
                                                      continuity, no branch flips; it stops at the first
                                                      sample not reached
    refine(...)                                       halve each step the model puts off the path by more
                                                      than a chordal tolerance (`deviation`)
    deviation(position, q_deg, segs, arc_mm)          how far each joint-linear step leaves its part of the path
    cycle_s(robot)                                    servoj's step on the robot's controller (8 or 2 ms)
    schedule(points, arc_mm, timing)                  the path in time: a speed profile from rest to rest, slower
                                                      round corners, ending on a whole controller cycle
    refusal(...)                                      the first sample that must stop the path, and why
    urscript(table, ...)                              movej to the start, then servoj every controller cycle to
                                                      where the schedule is then, joint-linear between samples

The arm is driven joint-linearly between samples (servoj interpolates in joint space), so what lies
between two samples is the model's joint-space chord: `deviation` measures it on the model.
"""
import time
from dataclasses import dataclass

import numpy as np
import pandas as pd
import torch

from pipeline.lib.project.columns import JCOMP_DEG, TARGET
from pipeline.lib.project.config import TOOL_SPEED_MAX, logger
from pipeline.lib.robot.kinematics import DTYPE
from pipeline.lib.robot.robots import TABLES
from pipeline.lib.runtime.compensation import solve
from pipeline.lib.runtime.paths import at, step_distance
from pipeline.lib.runtime.solvers import CHUNK, slices

CB3 = ("ur3", "ur5", "ur10")    # robots.py's arms on a CB3 controller (125 Hz); the others' run at 500 Hz
REFINE_ROUNDS = 12              # chord mode: halvings at most
MIN_STEP_MM = 1e-3              # chord mode: a step this short is not halved further
PROGRESS_EVERY = 1000          # a log line per this many samples solved (a path of 100 000: ~40 min)
MAX_CYCLES = 2 ** 24 - 1        # a path's servoj cycles: the script counts them in a float (32 bits: 2^24 + 1 is 2^24)
TURN_SIN = 1e-6                 # sin(φ/2) of a turn (2e-6 rad) below which a sample is straight: rounding on a line
                                # not along an axis gives ~1e-8, which must not slow the steps beside it
CHUNK_CYCLES = 1 << 20          # the script's cycles reckoned this many at a time (memory: ~50 MB a chunk)
SHARE_TOL = 1e-9                # a run's quadratic, as written, meets each cycle's share of its step within this
log = logger(__name__)
SOLVED = ["arc_mm"] + TARGET + JCOMP_DEG + ["residual_mm", "iterations", "converged", "orientation_residual_arcsec"]
PATH_COLUMNS = (["sample", "arc_mm", "t_s"] + TARGET + JCOMP_DEG
                + ["residual_mm", "iterations", "converged", "in_workspace", "uncertainty_mm",
                   "orientation_residual_arcsec"])


def solve_sample(model, q_deg: np.ndarray, target: np.ndarray, cfg: dict, robot, rot=None) -> tuple:
    """Joints (deg) that put the model's TCP on target (mm), solved from q_deg (the previous sample's
    solution) by `compensate.solver` within the joint limits -> (q_deg (6,), residual_mm, iterations,
    converged, orientation_residual_arcsec). rot (3, 3): the flange's orientation to reach too (a pose: six
    equations; compensation.solve), else the orientation residual is NaN."""
    s = solve(model, np.asarray(q_deg, float)[None], np.asarray(target, float)[None], cfg, robot, history=False,
              flange_rot=None if rot is None else np.asarray(rot, float)[None])
    arcsec = np.nan if s.orientation_arcsec is None else float(s.orientation_arcsec[0])
    return s.q_deg[0], float(np.linalg.norm(s.pred[0] - target)), int(s.iterations[0]), bool(s.converged[0]), arcsec


def solve_path(model, targets: np.ndarray, arc_mm: np.ndarray, q_start_deg, cfg: dict, robot,
               rots: np.ndarray | None = None) -> pd.DataFrame:
    """Each sample (targets (m, 3), arc_mm (m,), with rots (m, 3, 3) the flange's orientations too) solved
    from the previous sample's solution, the first from q_start_deg; it stops after the first sample not
    converged (the table then ends there)."""
    rows, q, t0 = [], np.asarray(q_start_deg, float), time.perf_counter()
    for i, (x, s) in enumerate(zip(targets, arc_mm)):
        q, *solved = solve_sample(model, q, x, cfg, robot, None if rots is None else rots[i])
        rows.append([s, *x, *q, *solved])
        if not solved[2]:
            break
        if (i + 1) % PROGRESS_EVERY == 0:
            log.info("path: %d of %d samples solved (%.0f s)", i + 1, len(targets), time.perf_counter() - t0)
    return pd.DataFrame(rows, columns=SOLVED)


STEP_PARTS = 8        # deviation: a step judged at 7 points along it (a review: at its middle alone, a coarse step
                      # that crossed an arc there passed 15.8 mm off it at a fifth of the way)


def model_position(model):
    """q_deg (k, 6) -> the model's TCP (k, 3) mm, solvers.CHUNK poses at a time."""
    def position(q_deg):
        q = torch.as_tensor(np.radians(np.asarray(q_deg, float)), dtype=DTYPE)
        with torch.no_grad():
            return torch.cat([model(q[s])[0] for s in slices(len(q), CHUNK)]).numpy()
    return position


def deviation(position, q_deg: np.ndarray, segs: list, arc_mm: np.ndarray, parts: int = STEP_PARTS) -> np.ndarray:
    """(m - 1,) mm: how far `position` puts each joint-linear step between samples q_deg (m, 6) at arc lengths
    arc_mm (m,) from the part of the path it spans (paths.step_distance): the worst of its points at 1/parts,
    2/parts, ... of the way (parts=2: its middle). A branch flip between two samples is tens of millimetres
    there; so is a step that cuts an arc short, or one that crosses the arc at its middle only."""
    q = np.asarray(q_deg, float)
    if len(q) < 2:
        return np.zeros(0)
    t = np.arange(1, parts) / parts
    inner = q[:-1, None] + t[None, :, None] * (q[1:] - q[:-1])[:, None]          # (m - 1, parts - 1, 6)
    p = np.asarray(position(inner.reshape(-1, 6))).reshape(len(q) - 1, parts - 1, 3)
    return np.max([step_distance(p[:, j], segs, arc_mm) for j in range(parts - 1)], axis=0)


def refine(model, table: pd.DataFrame, segs: list, chord_mm: float, cfg: dict, robot, rotations=None,
           max_samples: int | None = None) -> pd.DataFrame:
    """Chord mode: each step the model puts farther than chord_mm from the path (`deviation`) gets a sample
    at its arc middle, solved from the middle of its ends' joints (continuity); until none does, a step is
    MIN_STEP_MM short, or REFINE_ROUNDS rounds (then `refusal` judges what is left). rotations: arc_mm (k,)
    -> the flange's orientations there (k, 3, 3), for a path with orientation. A ValueError, before a round's
    solves, where it would make more than max_samples samples."""
    position = model_position(model)
    for k in range(REFINE_ROUNDS):
        q, arc = table[JCOMP_DEG].to_numpy(), table.arc_mm.to_numpy()
        bad = np.flatnonzero((deviation(position, q, segs, arc) > chord_mm) & (np.diff(arc) > MIN_STEP_MM))
        if not len(bad):
            break
        if max_samples is not None and len(table) + len(bad) > max_samples:
            raise ValueError(f"chord {chord_mm:g} mm: halving {k + 1} would make {len(table) + len(bad)} samples, "
                             f"more than path.max_samples ({max_samples}): a larger --chord")
        mid = (arc[bad] + arc[bad + 1]) / 2
        rows, rots = [], [None] * len(mid) if rotations is None else rotations(mid)
        for k, s, x, rot in zip(bad, mid, at(segs, mid), rots):
            qk, *solved = solve_sample(model, (q[k] + q[k + 1]) / 2, x, cfg, robot, rot)
            rows.append([s, *x, *qk, *solved])
        new = pd.DataFrame(rows, columns=SOLVED)
        table = pd.concat([table, new]).sort_values("arc_mm", kind="stable").reset_index(drop=True)
    return table


def cycle_s(robot) -> float:
    """servoj's step (s) on the robot's controller, the t the script gives it: a CB3's cycle, 8 ms (125 Hz: the UR3,
    UR5, UR10 of robots.py), an e-Series', UR20's or UR30's, 2 ms (500 Hz); a custom robot's 8 ms, a whole
    number of either controller's cycles."""
    return 0.002 if robot.name in TABLES and robot.name not in CB3 else 0.008


@dataclass(frozen=True)
class Timing:
    """How a path is timed: the TCP's speed along it (mm/s), its acceleration (mm/s²) from rest at the start,
    to rest at the end and round corners, the corners' junction deviation (mm: path.corner_mm) and the
    controller's cycle (s, cycle_s)."""
    speed_mm_s: float
    accel_mm_s2: float
    corner_mm: float
    cycle_s: float


def half_sines(points_mm: np.ndarray) -> np.ndarray:
    """(m - 2,) sin(φ/2) of the turn φ at each inner sample of points (m, 3) (0 on a straight)."""
    d = np.diff(np.asarray(points_mm, float), axis=0)
    u = d / np.maximum(np.linalg.norm(d, axis=1), 1e-300)[:, None]                 # (m - 1, 3) each step's direction
    return np.sqrt(np.clip(0.5 * (1 - np.einsum("ij,ij->i", u[:-1], u[1:])), 0.0, 1.0))


def step_accels(points_mm: np.ndarray, accel: float) -> np.ndarray:
    """(m - 1,) mm/s²: each step's acceleration along the path: accel, or half of it where either end turns
    (the other half is the turn's, which servoj makes within one cycle: the two together stay within accel)."""
    turns = np.concatenate([[False], half_sines(points_mm) > TURN_SIN, [False]])
    return np.where(turns[:-1] | turns[1:], accel / 2, accel)


def speed_profile(points_mm: np.ndarray, arc_mm: np.ndarray, t: Timing) -> np.ndarray:
    """(m,) mm/s: the TCP's speed at each sample, points (m, 3) along arc (m,): at rest at both ends, at most
    t.speed_mm_s and at most one step a controller cycle (so the cycles run along the joint-space chords the
    command checks; one that spans a sample cuts its corner by at most a cycle²/8), at a turn of φ between two steps at most
    sqrt(a δ c / (1 - c)), c = cos(φ/2) (the junction deviation rule: a 90° corner at 1.2 m/s² and 0.01 mm,
    5.4 mm/s), (a/2) cycle / (2 sin(φ/2)) (servoj turns the whole angle within one cycle: a velocity change of
    at most half the acceleration's) and sqrt(a r / 2), r = the shorter step over 2 sin(φ/2) (the centripetal
    limit of a sampled arc, whatever its spacing), and changing by at most each step's step_accels along the
    path (a forward and a backward pass: v² ≤ v_prev² + 2 a Δs)."""
    ds, a = np.diff(arc_mm), t.accel_mm_s2
    sin = half_sines(points_mm)                                                    # (m - 2,)
    c = np.sqrt(1 - sin ** 2)                                                      # cos(φ/2)
    acc = step_accels(points_mm, a)                                                # (m - 1,)
    with np.errstate(divide="ignore", invalid="ignore"):
        radius = np.minimum(ds[:-1], ds[1:]) / (2 * sin)                           # the turn's
        corner = np.minimum.reduce([np.sqrt(a * t.corner_mm * c / (1 - c)),       # inf on a straight
                                    a / 2 * t.cycle_s / (2 * sin),
                                    np.sqrt(a / 2 * radius),                       # and on a sampled arc at most
                                    np.minimum(ds[:-1], ds[1:]) / t.cycle_s])
    v = np.concatenate([[0.0], np.minimum(t.speed_mm_s, corner), [0.0]]) if len(ds) else np.zeros(len(arc_mm))
    for k in range(len(ds)):                                                       # forward: accelerate
        v[k + 1] = min(v[k + 1], np.sqrt(v[k] ** 2 + 2 * acc[k] * ds[k]))
    for k in range(len(ds) - 1, -1, -1):                                           # backward: decelerate
        v[k] = min(v[k], np.sqrt(v[k + 1] ** 2 + 2 * acc[k] * ds[k]))
    return v


def along(va, vb, top, ds, a, step, tau):
    """The arc (mm) a trapezoid has covered after tau s: from va up to top, at top, down to vb at a, over ds in
    step s (arrays of one shape, or numbers)."""
    t1, t2 = (top - va) / a, (top - vb) / a
    d1 = (top ** 2 - va ** 2) / (2 * a)
    s = np.where(tau <= t1, va * tau + a * tau ** 2 / 2,
                 np.where(tau <= step - t2, d1 + top * (tau - t1), ds - vb * (step - tau) - a * (step - tau) ** 2 / 2))
    return np.clip(s, 0.0, ds)


@dataclass(frozen=True)
class Schedule:
    """A path's motion in time: each step's trapezoid on speed_profile (ds, va, vb, top, step: its length, its
    first and last sample's speed, its peak, its time, its acceleration accel; (m - 1,) each), the factor
    stretch (≤ 1) by which the whole path is slowed to end on a whole controller cycle (n_cycles of them)."""
    ds: np.ndarray
    va: np.ndarray
    vb: np.ndarray
    top: np.ndarray
    step: np.ndarray
    stretch: float
    n_cycles: int
    cycle_s: float
    accel: np.ndarray

    @property
    def t_s(self) -> np.ndarray:
        """(m,) s: each sample's time along the path."""
        return np.concatenate([[0.0], np.cumsum(self.step)]) / self.stretch

    @property
    def peak_mm_s(self) -> np.ndarray:
        """(m - 1,) mm/s: the TCP's top speed within each step, as driven."""
        return self.top * self.stretch

    def cycle_arcs(self, lo: int = 0, hi: int | None = None) -> np.ndarray:
        """(hi - lo,) mm: the arc the path has reached at the end of controller cycles lo + 1 .. hi (default: all
        n_cycles; the last: its end)."""
        hi = self.n_cycles if hi is None else hi
        start = np.concatenate([[0.0], np.cumsum(self.step)])                     # (m,) each step's start, unstretched
        tau = np.arange(lo + 1, hi + 1) * self.cycle_s * self.stretch
        if hi == self.n_cycles:
            tau[-1] = start[-1]
        k = np.clip(np.searchsorted(start, tau, side="right") - 1, 0, len(self.ds) - 1)
        return np.concatenate([[0.0], np.cumsum(self.ds)])[k] + along(
            self.va[k], self.vb[k], self.top[k], self.ds[k], self.accel[k], self.step[k], tau - start[k])


def schedule(points_mm: np.ndarray, arc_mm: np.ndarray, t: Timing) -> Schedule:
    """The path's Schedule: each step on its trapezoid (from its first sample's speed up to at most the path's,
    and one step a cycle, down to its last's at the acceleration), the whole slowed to a whole number of
    controller cycles. A ValueError where the path would take more cycles than the script's counter holds
    exactly (a speed far too low), or where the speed is beyond any tool speed (a slip of unit)."""
    if not t.speed_mm_s <= 1000 * TOOL_SPEED_MAX:
        raise ValueError(f"speed {float(t.speed_mm_s)!r} mm/s: beyond {1000 * TOOL_SPEED_MAX:g} mm/s, the highest tool speed "
                         "UR's safety configuration takes (mm/s: a speed in m/s?)")
    points_mm, arc_mm = np.asarray(points_mm, float), np.asarray(arc_mm, float)
    ds, v, a = np.diff(arc_mm), speed_profile(points_mm, arc_mm, t), step_accels(points_mm, t.accel_mm_s2)
    va, vb = v[:-1], v[1:]
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        top = np.minimum.reduce([np.full(len(ds), float(t.speed_mm_s)), ds / t.cycle_s,
                                 np.sqrt((2 * a * ds + va ** 2 + vb ** 2) / 2)])
        step = np.where(ds > 0, (2 * top - va - vb) / a + (ds - (2 * top ** 2 - va ** 2 - vb ** 2) / (2 * a)) / top, 0.0)
        total = float(step.sum())
        cycles = max(1.0, np.ceil(np.round(total / t.cycle_s, 9)))
    if not cycles <= MAX_CYCLES:
        raise ValueError(f"speed {t.speed_mm_s:g} mm/s: the path of {arc_mm[-1] - arc_mm[0]:.3f} mm would take more "
                         f"than {MAX_CYCLES} controller cycles (URScript's 32-bit float counts no further): a higher speed")
    return Schedule(ds, va, vb, top, step, total / (cycles * t.cycle_s) if total > 0 else 1.0, int(cycles),
                    t.cycle_s, a)


def finish(table: pd.DataFrame, workspace, timed: Schedule) -> pd.DataFrame:
    """path.csv's table (PATH_COLUMNS): samples numbered from 1, each one's time along the path (s: the
    table's Schedule), in_workspace and uncertainty_mm at its joints."""
    table = table.copy()
    table.insert(0, "sample", np.arange(1, len(table) + 1))
    table.insert(2, "t_s", timed.t_s)
    table["uncertainty_mm"], table["in_workspace"] = workspace(table[JCOMP_DEG].to_numpy())
    table["converged"] = table.converged.astype(bool)
    return table[PATH_COLUMNS]


def joint_speeds(robot, setting) -> np.ndarray:
    """The joint speed limits (6,) deg/s: path.joint_speed_deg_s (a number, or 6: none above the robot's own,
    where known), else the robot's."""
    v = np.degrees(np.asarray(robot.velocity_rad_s, float))
    if setting is not None:
        given = np.broadcast_to(np.asarray(setting, float), (6,)).copy()
        over = np.flatnonzero((v > 0) & (given > v))
        if len(over):
            j = int(over[0])
            raise ValueError(f"params.yaml path.joint_speed_deg_s: joint {j + 1} at {given[j]:g} deg/s, beyond the "
                             f"{robot.name}'s own {v[j]:.0f} deg/s (robots.py): a path may only be slower")
        return given
    if not (v > 0).all():
        raise ValueError("params.yaml path.joint_speed_deg_s: the robot's joint speed limits are unknown "
                         "(a custom robot): set them, here or as robot.dh.velocity_deg_s")
    return v


def beyond_reach(targets: np.ndarray, arc_mm: np.ndarray, reach_mm: float) -> str | None:
    """The first sample (numbered from 1) farther from the base than the arm reaches, said; else None."""
    far = np.flatnonzero(np.linalg.norm(targets, axis=1) > reach_mm)
    if not len(far):
        return None
    k = int(far[0])
    return (f"sample {k + 1} (arc {arc_mm[k]:.1f} mm): target {np.linalg.norm(targets[k]):.1f} mm from the base, "
            f"beyond the arm's reach of {reach_mm:.1f} mm")


def refusal(table: pd.DataFrame, n_samples: int, limits_deg: np.ndarray, tol_mm: float, dev: np.ndarray,
            max_deviation_mm: float, peak_mm_s: np.ndarray, speeds_deg_s: np.ndarray, workspace=None) -> str | None:
    """Why the path must stop, naming its first sample that must not be driven (numbered from 1), or None:
    not reached (solve_path stops at such a sample; refine's samples in between may be one too), beyond the
    joint limits, a joint faster than its speed limit within a step (joint-linear from sample to sample at the
    TCP's top speed in it, peak_mm_s: the whole path's Schedule's), or a joint-space step whose
    chord leaves the path by more than max_deviation_mm (dev: `deviation`: a branch flip), and, with a
    workspace, outside the trained workspace; the kinds found after the first are named with their first
    sample."""
    found = []                                           # (sample index, kind, message)
    arc, q = table.arc_mm.to_numpy(), table[JCOMP_DEG].to_numpy()
    name = lambda k: f"sample {k + 1} (arc {arc[k]:.1f} mm)"
    unreached = np.flatnonzero(~table.converged.to_numpy(bool))
    m = int(unreached[0]) if len(unreached) else len(table)        # the samples reached before the first not
    if m < len(table):
        o = table.orientation_residual_arcsec.iloc[m] if "orientation_residual_arcsec" in table else np.nan
        off = "" if np.isnan(o) else f"; the flange's orientation {o:.2f} arcsec off"
        start = "the start joints" if m == 0 else f"sample {m}'s joints"          # there is no sample 0
        rest = n_samples - m - 1
        after = (f"solved from {start}" + (f"; the {rest} samples after it were not solved" if rest else "")
                 if m == len(table) - 1 else f"solved between samples {m} and {m + 2} (chord mode)")
        found.append((m, "not reached", f"{name(m)}: not reached (residual {table.residual_mm.iloc[m]:.4f} mm, "
                                        f"tolerance {tol_mm:g} mm{off}), {after}"))
    lo, hi = np.asarray(limits_deg, float).T
    beyond = np.argwhere((q[:m] < lo) | (q[:m] > hi))
    if len(beyond):
        k, j = map(int, beyond[0])
        found.append((k, "beyond the joint limits",
                      f"{name(k)}: joint {j + 1} at {q[k, j]:.1f}°, beyond its limits [{lo[j]:g}, {hi[j]:g}]°"))
    ds, peak = np.diff(arc[:m]), np.asarray(peak_mm_s, float)[:max(m - 1, 0)]
    with np.errstate(divide="ignore", invalid="ignore"):
        rate = np.abs(np.diff(q[:m], axis=0)) / ds[:, None] * peak[:, None]           # deg/s at the step's top speed
    fast = np.argwhere(rate > speeds_deg_s)
    if len(fast):
        k, j = map(int, fast[0])
        found.append((k + 1, "a joint too fast",
                      f"{name(k + 1)}: joint {j + 1} turns {abs(q[k + 1, j] - q[k, j]):.2f}° from sample {k + 1} over "
                      f"{ds[k]:.3f} mm at up to {peak[k]:.1f} mm/s ({rate[k, j]:.0f}°/s, beyond its "
                      f"{speeds_deg_s[j]:.0f}°/s): a branch flip, or a slower --speed"))
    off = np.flatnonzero(dev[:max(m - 1, 0)] > max_deviation_mm)
    if len(off):
        k = int(off[0])
        found.append((k + 1, "leaving the path",
                      f"samples {k + 1}-{k + 2} (arc {arc[k]:.1f}-{arc[k + 1]:.1f} mm): the joint-space step between "
                      f"them leaves the path by {dev[k]:.2f} mm (path.max_deviation_mm "
                      f"{max_deviation_mm:g}): a branch flip, or a spacing too coarse for the curve?"))
    outside = np.flatnonzero(~table.in_workspace.to_numpy(bool)[:m]) if workspace is not None else []
    if len(outside):
        k = int(outside[0])
        radii = float(workspace.distance(q[k])[0] / workspace.radius)
        found.append((k, "outside the trained workspace",
                      f"{name(k)}: outside the trained workspace ({radii:.2f} workspace radii from the nearest "
                      f"training pose; {len(outside)} of {m} samples are), where the correction has faded to the "
                      "calibration: rerun with --allow-outside-workspace to write it with those samples flagged"))
    if not found:
        return None
    found.sort(key=lambda f: f[0])
    return found[0][2] + "".join(f"; then {kind} at sample {k + 1}" for k, kind, _ in found[1:])


def fmt(values) -> str:
    """Joint angles (deg) as URScript's list of radians: only digits, signs and points."""
    return "[" + ", ".join(f"{v:.9f}" for v in np.radians(np.asarray(values, float))) + "]"


def written(x: float) -> float:
    """x as the script writes it (fmt_share) and reads it back."""
    return float(fmt_share(x))


def fmt_share(x: float) -> str:
    """A share, or a share's change a cycle, as URScript's number: digits, a sign, a point (17 places)."""
    return f"{float(x):.17f}"


def runs(chord: np.ndarray, f: np.ndarray) -> list[tuple]:
    """The cycles' targets (chord (K,): the step k from sample k - 1 to k each is on; f (K,): its share of that
    step) as runs the script loops over: (step, f0, df, d2, n), n cycles at the shares f0 + i df + i² d2,
    i = 1..n, each on one step, the coefficients as written (fmt_share) meeting every cycle's share within
    SHARE_TOL: a speed held or a constant acceleration is one run (a trapezoid's phase on one step)."""
    out, i, K = [], 0, len(f)
    while i < K:
        same = 1
        while same < 3 and i + same < K and chord[i + same] == chord[i]:
            same += 1
        g = np.zeros(3)
        g[:same] = f[i:i + same]
        if same == 3:                                      # through three cycles' shares: k = 1, 2, 3
            d2 = (g[2] - 2 * g[1] + g[0]) / 2
            df = g[1] - g[0] - 3 * d2
        elif same == 2:
            d2, df = 0.0, g[1] - g[0]
        else:
            d2, df = 0.0, g[0]
        f0, df, d2 = written(g[0] - df - d2), written(df), written(d2)
        at = lambda k: f0 + k * df + k * k * d2
        n = 0
        while i + n < K and chord[i + n] == chord[i] and abs(at(n + 1) - f[i + n]) <= SHARE_TOL:
            n += 1
        if n == 0:                                         # the rounding of the coefficients: one cycle, exactly
            f0, df, d2, n = 0.0, written(f[i]), 0.0, 1
        out.append((int(chord[i]), f0, df, d2, n))
        i += n
    return out


def urscript(table: pd.DataFrame, timed: Schedule, lookahead_s: float, gain: int, acc: float, vel: float) -> str:
    """The compensated path: movej (acc rad/s², vel rad/s) to its first sample, then servoj every controller
    cycle (timed.cycle_s, cycle_s) to where the path's Schedule has reached at that cycle's end (cycle_arcs),
    the joints on the line from sample to sample there: `servo_line(a, b, f0, df, d2, n)`, n cycles at the shares
    f0 + i df + i² d2 of the line from a to b (`runs`); the last sample held for the lookahead, then stopj. Only
    numbers formatted here and this fixed text reach it."""
    cycle = timed.cycle_s
    q, arc = table[JCOMP_DEG].to_numpy(), table.arc_mm.to_numpy()
    hold = int(np.ceil(lookahead_s / cycle - 1e-9))
    outside = int((~table.in_workspace.to_numpy(bool)).sum())
    mix = ", ".join(f"a[{j}] + s * (b[{j}] - a[{j}])" for j in range(6))
    lines = [f"# compensated path by `python -m pipeline.commands.path`: {len(table)} samples over "
             f"{float(table.arc_mm.iloc[-1]):.3f} mm at up to {float(timed.peak_mm_s.max(initial=0.0)):.3f} mm/s "
             f"({float(timed.accel.max(initial=0.0)):.1f} mm/s^2 from and to rest), "
             f"{float(table.t_s.iloc[-1]):.3f} s; joints in rad",
             f"# residual max {float(table.residual_mm.max()):.6f} mm; {outside} samples outside the trained workspace"]
    arcsec = table.orientation_residual_arcsec.to_numpy(float)
    if not np.isnan(arcsec).all():
        lines.append(f"# the flange's orientation held along the path: residual max {float(np.nanmax(arcsec)):.3f} arcsec")
    lines += ["def compensated_path():",
              "  def servo_line(a, b, f0, df, d2, n):",
              "    # n controller cycles on the line from joints a to b: one servoj a cycle, at the share f0 + i df + i^2 d2",
              "    i = 1.0",
              "    while i <= n:",
              "      s = f0 + i * df + i * i * d2",
              f"      servoj([{mix}], t={float(cycle):.3f}, lookahead_time={float(lookahead_s):.3f}, gain={int(gain)})",
              "      i = i + 1.0",
              "    end",
              "  end",
              f"  movej({fmt(q[0])}, a={float(acc):.6f}, v={float(vel):.6f})"]
    noted = set()
    for lo in range(0, timed.n_cycles, CHUNK_CYCLES):                            # memory: a chunk's cycles at a time
        at = timed.cycle_arcs(lo, min(lo + CHUNK_CYCLES, timed.n_cycles))       # (K,) mm
        chord = np.clip(np.searchsorted(arc, at, side="left"), 1, len(arc) - 1)  # (K,) from sample chord - 1 to chord
        share = np.clip((at - arc[chord - 1]) / (arc[chord] - arc[chord - 1]), 0.0, 1.0)
        for k, f0, df, d2, n in runs(chord, share):
            if k not in noted and not table.in_workspace.iloc[k]:
                lines.append(f"  # sample {k + 1}: outside the trained workspace (uncertainty "
                             f"{float(table.uncertainty_mm.iloc[k]):.3f} mm)")
            noted.add(k)
            lines.append(f"  servo_line({fmt(q[k - 1])}, {fmt(q[k])}, {fmt_share(f0)}, {fmt_share(df)}, "
                         f"{fmt_share(d2)}, {n})")
    lines += [f"  servo_line({fmt(q[-1])}, {fmt(q[-1])}, 0.0, 0.0, 0.0, {hold})", f"  stopj({float(acc):.6f})", "end", ""]
    return "\n".join(lines)

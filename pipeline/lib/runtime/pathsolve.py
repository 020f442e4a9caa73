"""A path compensated sample by sample, checked, and the URScript that drives it (docs/robot-cell.md,
"Compensating a path"); for `python -m pipeline.commands.path`, the service's compensate_path and bench path.

    solve_sample(model, q_deg, target, cfg, robot)    the one per-sample solve (with rot: a pose)
    solve_path(model, targets, arc_mm, q_start, ...)  every sample from the previous sample's solution:
                                                      continuity, no branch flips; it stops at the first
                                                      sample not reached
    refine(...)                                       halve each step whose joint-space middle leaves the
                                                      path by more than a chordal tolerance
    deviation(position, q_deg, segs)                  how far each joint-linear step's middle leaves the path
    cycle_s(robot)                                    servoj's step on the robot's controller (8 or 2 ms)
    servo_times(points, arc_mm, timing)               each step's servoj time (a speed profile from rest to
                                                      rest, slower round corners), in whole controller cycles
    refusal(...)                                      the first sample that must stop the path, and why
    urscript(table, ...)                              movej to the start, then servoj every controller cycle,
                                                      joint-linear from sample to sample

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
from pipeline.lib.runtime.paths import at, distance
from pipeline.lib.runtime.solvers import CHUNK, slices

CB3 = ("ur3", "ur5", "ur10")    # robots.py's arms on a CB3 controller (125 Hz); the others' run at 500 Hz
REFINE_ROUNDS = 12              # chord mode: halvings at most
MIN_STEP_MM = 1e-3              # chord mode: a step this short is not halved further
PROGRESS_EVERY = 1000          # a log line per this many samples solved (a path of 100 000: ~40 min)
MAX_CYCLES = 2 ** 24 - 1        # a step's servoj cycles: the script counts them in a float (32 bits: 2^24 + 1 is 2^24)
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


def model_position(model):
    """q_deg (k, 6) -> the model's TCP (k, 3) mm, solvers.CHUNK poses at a time."""
    def position(q_deg):
        q = torch.as_tensor(np.radians(np.asarray(q_deg, float)), dtype=DTYPE)
        with torch.no_grad():
            return torch.cat([model(q[s])[0] for s in slices(len(q), CHUNK)]).numpy()
    return position


def deviation(position, q_deg: np.ndarray, segs: list) -> np.ndarray:
    """(m - 1,) mm: how far `position` puts the middle of each joint-linear step between samples q_deg
    (m, 6) from the path. A branch flip between two samples is tens of millimetres there."""
    q = np.asarray(q_deg, float)
    if len(q) < 2:
        return np.zeros(0)
    return distance(position((q[:-1] + q[1:]) / 2), segs)


def refine(model, table: pd.DataFrame, segs: list, chord_mm: float, cfg: dict, robot, rotations=None,
           max_samples: int | None = None) -> pd.DataFrame:
    """Chord mode: each step whose middle the model puts farther than chord_mm from the path gets a sample
    at its arc middle, solved from the middle of its ends' joints (continuity); until none does, a step is
    MIN_STEP_MM short, or REFINE_ROUNDS rounds (then `refusal` judges what is left). rotations: arc_mm (k,)
    -> the flange's orientations there (k, 3, 3), for a path with orientation. A ValueError, before a round's
    solves, where it would make more than max_samples samples."""
    position = model_position(model)
    for k in range(REFINE_ROUNDS):
        q, arc = table[JCOMP_DEG].to_numpy(), table.arc_mm.to_numpy()
        bad = np.flatnonzero((deviation(position, q, segs) > chord_mm) & (np.diff(arc) > MIN_STEP_MM))
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


def speed_profile(points_mm: np.ndarray, arc_mm: np.ndarray, t: Timing) -> np.ndarray:
    """(m,) mm/s: the TCP's speed at each sample, points (m, 3) along arc (m,): at rest at both ends, at most
    t.speed_mm_s, at a turn of φ between two steps at most sqrt(a δ c / (1 - c)), c = cos(φ/2) (the junction
    deviation rule: a 90° corner at 1.2 m/s² and 0.01 mm, 5.4 mm/s) and sqrt(a r), r = the shorter step over
    2 sin(φ/2) (the centripetal limit of a sampled arc, whatever its spacing), and changing by at most
    t.accel_mm_s2 along the path (a forward and a backward pass: v² ≤ v_prev² + 2 a Δs)."""
    ds = np.diff(arc_mm)                                                           # (m - 1,)
    d = np.diff(np.asarray(points_mm, float), axis=0)
    u = d / np.maximum(np.linalg.norm(d, axis=1), 1e-300)[:, None]                 # (m - 1, 3) each step's direction
    c = np.sqrt(np.clip(0.5 * (1 + np.einsum("ij,ij->i", u[:-1], u[1:])), 0.0, 1.0))   # cos(φ/2) at inner samples
    with np.errstate(divide="ignore", invalid="ignore"):
        radius = np.minimum(ds[:-1], ds[1:]) / (2 * np.sqrt(np.clip(1 - c ** 2, 0.0, 1.0)))   # the turn's, sin(φ/2)
        corner = np.minimum(np.sqrt(t.accel_mm_s2 * t.corner_mm * c / (1 - c)),          # inf on a straight
                            np.sqrt(t.accel_mm_s2 * radius))                           # and on a sampled arc at most
    v = np.concatenate([[0.0], np.minimum(t.speed_mm_s, corner), [0.0]]) if len(ds) else np.zeros(len(arc_mm))
    for k in range(len(ds)):                                                       # forward: accelerate
        v[k + 1] = min(v[k + 1], np.sqrt(v[k] ** 2 + 2 * t.accel_mm_s2 * ds[k]))
    for k in range(len(ds) - 1, -1, -1):                                           # backward: decelerate
        v[k] = min(v[k], np.sqrt(v[k + 1] ** 2 + 2 * t.accel_mm_s2 * ds[k]))
    return v


def trapezoids(points_mm: np.ndarray, arc_mm: np.ndarray, t: Timing) -> tuple:
    """Each step's trapezoid on speed_profile: (Δs, its first sample's speed, its last's, its peak, its time),
    (m - 1,) each: from the first speed up to at most t.speed_mm_s and down to the last at t.accel_mm_s2."""
    ds, v, a = np.diff(arc_mm), speed_profile(points_mm, arc_mm, t), t.accel_mm_s2
    va, vb = v[:-1], v[1:]
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        top = np.minimum(t.speed_mm_s, np.sqrt((2 * a * ds + va ** 2 + vb ** 2) / 2))
        step = np.where(ds > 0, (2 * top - va - vb) / a + (ds - (2 * top ** 2 - va ** 2 - vb ** 2) / (2 * a)) / top, 0.0)
    return ds, va, vb, top, step


def step_fractions(va: float, vb: float, top: float, ds: float, a: float, n: int) -> np.ndarray:
    """(n,) the share of a step's length reached at the end of each of its n cycles, moving on its trapezoid
    (from va up to top, at top, down to vb, at a) stretched evenly over the n cycles: the last is 1."""
    t1, t2 = (top - va) / a, (top - vb) / a
    d1, d2 = (top ** 2 - va ** 2) / (2 * a), (top ** 2 - vb ** 2) / (2 * a)
    T = t1 + t2 + max(ds - d1 - d2, 0.0) / top
    tau = T * np.arange(1, n + 1) / n
    s = np.where(tau <= t1, va * tau + a * tau ** 2 / 2,
                 np.where(tau <= T - t2, d1 + top * (tau - t1), ds - vb * (T - tau) - a * (T - tau) ** 2 / 2))
    f = np.clip(s / ds, 0.0, 1.0)
    f[-1] = 1.0
    return f


def step_cycles(points_mm: np.ndarray, arc_mm: np.ndarray, t: Timing) -> tuple:
    """Each step's whole controller cycles (m - 1,) on its trapezoid (`trapezoids`: from its first sample's speed
    up to at most the path's and down to its last's at the acceleration), at least one, rounded up: no step
    faster than the profile; and the trapezoids. A ValueError where a step would take more cycles than the
    script's counter holds exactly (a speed far too low), or where the speed is beyond any tool speed (a slip
    of unit)."""
    if not t.speed_mm_s <= 1000 * TOOL_SPEED_MAX:
        raise ValueError(f"speed {float(t.speed_mm_s)!r} mm/s: beyond {1000 * TOOL_SPEED_MAX:g} mm/s, the highest tool speed "
                         "UR's safety configuration takes (mm/s: a speed in m/s?)")
    ds, va, vb, top, step = trapezoids(points_mm, arc_mm, t)
    with np.errstate(over="ignore", invalid="ignore"):
        cycles = np.maximum(1, np.ceil(np.round(step / t.cycle_s, 9)))
    slow = np.flatnonzero(~(cycles <= MAX_CYCLES))
    if len(slow):
        raise ValueError(f"speed {t.speed_mm_s:g} mm/s: a step of {ds[slow[0]]:.3f} mm would take more "
                         f"than {MAX_CYCLES} controller cycles (URScript's 32-bit float counts no further): a higher speed")
    return cycles, (ds, va, vb, top)


def servo_times(points_mm: np.ndarray, arc_mm: np.ndarray, t: Timing) -> np.ndarray:
    """(m - 1,) s: each step's servoj time, its whole cycles (step_cycles) times the controller's cycle."""
    return step_cycles(points_mm, arc_mm, t)[0] * t.cycle_s


def finish(table: pd.DataFrame, workspace, timing: Timing) -> pd.DataFrame:
    """path.csv's table (PATH_COLUMNS): samples numbered from 1, each one's time along the path (s: servo_times),
    in_workspace and uncertainty_mm at its joints."""
    table = table.copy()
    table.insert(0, "sample", np.arange(1, len(table) + 1))
    table.insert(2, "t_s", np.concatenate([[0.0], np.cumsum(servo_times(table[TARGET].to_numpy(),
                                                                        table.arc_mm.to_numpy(), timing))]))
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
            max_deviation_mm: float, t_s: np.ndarray, speed_mm_s: float, speeds_deg_s: np.ndarray,
            workspace=None) -> str | None:
    """Why the path must stop, naming its first sample that must not be driven (numbered from 1), or None:
    not reached (solve_path stops at such a sample; refine's samples in between may be one too), beyond the
    joint limits, a joint step faster than the joint's speed limit as timed (t_s: each sample's time along the whole
    path, servo_times', at speed_mm_s), or a joint-space step whose
    middle leaves the path by more than max_deviation_mm (dev: `deviation`: a branch flip), and, with a
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
    dt = np.diff(np.asarray(t_s, float)[:m])
    rate = np.abs(np.diff(q[:m], axis=0)) / dt[:, None]                  # deg/s
    fast = np.argwhere(rate > speeds_deg_s)
    if len(fast):
        k, j = map(int, fast[0])
        found.append((k + 1, "a joint too fast",
                      f"{name(k + 1)}: joint {j + 1} turns {abs(q[k + 1, j] - q[k, j]):.2f}° from sample {k + 1} in "
                      f"{dt[k]:.3f} s ({rate[k, j]:.0f}°/s, beyond its {speeds_deg_s[j]:.0f}°/s at "
                      f"{speed_mm_s:g} mm/s): a branch flip?"))
    off = np.flatnonzero(dev[:max(m - 1, 0)] > max_deviation_mm)
    if len(off):
        k = int(off[0])
        found.append((k + 1, "leaving the path",
                      f"samples {k + 1}-{k + 2} (arc {arc[k]:.1f}-{arc[k + 1]:.1f} mm): the joint-space step between "
                      f"them leaves the path by {dev[k]:.2f} mm at its middle (path.max_deviation_mm "
                      f"{max_deviation_mm:g}): a branch flip?"))
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


def urscript(table: pd.DataFrame, timing: Timing, lookahead_s: float, gain: int, acc: float, vel: float) -> str:
    """The compensated path: movej (acc rad/s², vel rad/s) to its first sample, then each step driven by
    servoj every controller cycle (timing.cycle_s, cycle_s) over the step's time (`servo_times`), the joints on
    the line from sample to sample: at one speed where the step's profile is (`servo_step(a, b, n)`), else cycle
    by cycle along its trapezoid (`step_fractions`: one servo_step of one cycle each, from rest, to rest, round
    a corner); the last sample held for the lookahead, then stopj. Only numbers formatted here and this fixed
    text reach it."""
    cycle = timing.cycle_s
    q, points, arc = table[JCOMP_DEG].to_numpy(), table[TARGET].to_numpy(), table.arc_mm.to_numpy()
    cycles, (ds, va, vb, top) = step_cycles(points, arc, timing)
    even = np.isclose(va, top, rtol=1e-9, atol=0) & np.isclose(vb, top, rtol=1e-9, atol=0) | (ds <= 0)
    hold = int(np.ceil(lookahead_s / cycle - 1e-9))
    outside = int((~table.in_workspace.to_numpy(bool)).sum())
    mix = ", ".join(f"a[{j}] + s * (b[{j}] - a[{j}])" for j in range(6))
    lines = [f"# compensated path by `python -m pipeline.commands.path`: {len(table)} samples over "
             f"{float(table.arc_mm.iloc[-1]):.3f} mm at {float(timing.speed_mm_s):.3f} mm/s "
             f"({float(timing.accel_mm_s2):.1f} mm/s^2 from and to rest), "
             f"{float(table.t_s.iloc[-1]):.3f} s; joints in rad",
             f"# residual max {float(table.residual_mm.max()):.6f} mm; {outside} samples outside the trained workspace"]
    arcsec = table.orientation_residual_arcsec.to_numpy(float)
    if not np.isnan(arcsec).all():
        lines.append(f"# the flange's orientation held along the path: residual max {float(np.nanmax(arcsec)):.3f} arcsec")
    lines += ["def compensated_path():",
             "  def servo_step(a, b, n):",
             "    # from joints a to b in n controller cycles, joint-linear: one servoj a cycle",
             "    i = 1.0",
             "    while i <= n:",
             "      s = i / n",
             f"      servoj([{mix}], t={float(cycle):.3f}, lookahead_time={float(lookahead_s):.3f}, gain={int(gain)})",
             "      i = i + 1.0",
             "    end",
             "  end",
             f"  movej({fmt(q[0])}, a={float(acc):.6f}, v={float(vel):.6f})"]
    for k in range(1, len(q)):
        if not table.in_workspace.iloc[k]:
            lines.append(f"  # sample {k + 1}: outside the trained workspace (uncertainty "
                         f"{float(table.uncertainty_mm.iloc[k]):.3f} mm)")
        n = int(cycles[k - 1])
        if even[k - 1] or n == 1:
            lines.append(f"  servo_step({fmt(q[k - 1])}, {fmt(q[k])}, {n})")
            continue
        f = step_fractions(va[k - 1], vb[k - 1], top[k - 1], ds[k - 1], timing.accel_mm_s2, n)
        via = q[k - 1] + f[:, None] * (q[k] - q[k - 1])                              # (n, 6) deg: a cycle's end each
        via[-1] = q[k]
        lines += [f"  servo_step({fmt(a)}, {fmt(b)}, 1)" for a, b in zip(np.vstack([q[k - 1], via[:-1]]), via)]
    lines += [f"  servo_step({fmt(q[-1])}, {fmt(q[-1])}, {hold})", f"  stopj({float(acc):.6f})", "end", ""]
    return "\n".join(lines)

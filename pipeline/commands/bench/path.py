"""`bench path`: a path compensated sample by sample against its waypoints alone, judged on the twin along
the whole motion (issue 36). Writes reports/bench/path.json and reports/bench/path_deviation.png. Needs a
finished `dvc repro` on the twin's campaign (the model, workspace and frame; compensate.twin).

Paths (PATHS, base frame, mm): a 400 mm straight seam and a 200 mm-diameter circle (two movec) inside
the trained workspace, and a program-like path at the twin's side (lines, an arc, a corner), outside it.
Cases, each judged every FINE_MM along the motion:
  uncompensated  the controller's movel/movec on its nominal kinematics (nominal DH and the frame stage's
                 tool): the TCP interpolated on the path, each point's joints by nominal IK, continued from
                 the point before; the arm is where the twin's true kinematics puts those joints
  waypoints      today's `program`: the waypoints (ends and via points) compensated, then the controller's
                 movel/movec between the nominal positions of the compensated joints, as above
  compensated    `path`: resampled at a spacing, every sample compensated from the one before
                 (lib/runtime/pathsolve.py), the arm driven joint-linearly between samples (servoj, movej)
The deviation is the distance of the arm's TCP (the twin, noise-free, in the model's base frame by the
fitted frame) from the intended path: mean and max along it, the samples and what lies between them.
"""
import time
from types import SimpleNamespace

import numpy as np
import pandas as pd

from pipeline.commands.bench.common import BENCH, ROOT, machine
from pipeline.lib.learning.checkpoint import load_model
from pipeline.lib.learning.model import PhysicsOnly, served
from pipeline.lib.learning.workspace import Workspace
from pipeline.lib.project.artifacts import FRAME_JSON, MODEL_WEIGHTS, WORKSPACE_JSON
from pipeline.lib.project.columns import JCOMP_DEG, JOINTS_DEG, TARGET
from pipeline.lib.project.config import load_params, logger, read_json, write_json
from pipeline.lib.reporting.figures import _plt, save
from pipeline.lib.robot.frames import to_base
from pipeline.lib.robot.geometry import theory_geometry
from pipeline.lib.robot.kinematics import DHChain, fk_numpy
from pipeline.lib.robot.robots import load_robot
from pipeline.lib.robot.tcp import at_tcp, probe_offsets
from pipeline.lib.runtime.paths import at, distance, resample, segments
from pipeline.lib.runtime.pathsolve import deviation, model_position, refine, solve_path
from pipeline.lib.runtime.waypoints import compensate_program
from pipeline.lib.sim.twin import Twin, sample_poses

log = logger(__name__)
FINE_MM = 0.25                        # the motion judged this often along the path
SPACINGS = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0)
CHORD_MM = 0.01                       # the chord mode's tolerance, from the coarsest spacing
GOALS = {"paths": ["seam", "circle"], "spacing_mm": 1.0, "mean_mm": 0.10, "max_mm": 0.30}


def arc_via(centre, radius, a0, a1) -> list:
    """The via point (the middle) and the end of an arc in the z = centre plane, angles in degrees."""
    at = lambda a: np.asarray(centre, float) + radius * np.array([np.cos(np.radians(a)), np.sin(np.radians(a)), 0.0])
    return [at((a0 + a1) / 2), at(a1)]


# name: (points, moves, the arm's joints at the start (deg): a training pose near it; the side's, the twin's
# side region); the seam and the circle lie inside the trained workspace, the side path outside it
PATHS = {
    "seam": (np.array([[-650.0, -200.0, 250.0], [-650.0, 200.0, 250.0]]), ["", "movel"],
             [2.5, -60.4, 91.1, -182.3, -61.2, -100.7]),
    "circle": (np.array([[-450.0, 0.0, 250.0], *arc_via([-550.0, 0.0, 250.0], 100.0, 0, 180),
                         *arc_via([-550.0, 0.0, 250.0], 100.0, 180, 360)]), ["", "via", "movec", "via", "movec"],
               [-19.8, -63.6, 81.1, 88.5, 105.4, -155.0]),
    "side": (np.array([[150.0, -500.0, 250.0], [350.0, -500.0, 250.0], *arc_via([350.0, -440.0, 250.0], 60.0, -90, 0),
                       [410.0, -300.0, 250.0], [410.0, -300.0, 150.0]]),
             ["", "movel", "via", "movec", "movel", "movel"], None),
}


def nominal_controller(geometry: dict):
    """The controller's nominal kinematics seen as a model (its IK: the same solver on them)."""
    return PhysicsOnly(SimpleNamespace(physics=DHChain(geometry)))


def controller_move(nominal, segs, q_start, cfg, robot) -> tuple[np.ndarray, np.ndarray]:
    """The controller's movel/movec: the TCP on segs every FINE_MM, its joints by nominal IK, each from the
    point before -> (arc_mm (k,), q_deg (k, 6))."""
    targets, arc = resample(segs, FINE_MM)
    t = solve_path(nominal, targets, arc, q_start, cfg, robot)
    if len(t) < len(arc) or not t.converged.all():
        raise RuntimeError(f"nominal IK did not converge at arc {t.arc_mm.iloc[-1]:.1f} mm")
    return arc, t[JCOMP_DEG].to_numpy()


def joint_motion(arc: np.ndarray, q: np.ndarray, step_mm: float = FINE_MM) -> tuple[np.ndarray, np.ndarray]:
    """The arm driven joint-linearly between samples (arc (m,), q (m, 6)), every step_mm or finer ->
    (arc (k,), q (k, 6)), every sample included."""
    a, out = [arc[:1]], [q[:1]]
    for k in range(len(arc) - 1):
        n = max(1, int(np.ceil((arc[k + 1] - arc[k]) / step_mm - 1e-9)))
        u = np.arange(1, n + 1) / n
        a.append(arc[k] + u * (arc[k + 1] - arc[k]))
        out.append(q[k] + u[:, None] * (q[k + 1] - q[k]))
    return np.concatenate(a), np.concatenate(out)


def stats(d: np.ndarray) -> dict:
    return {"mean_mm": float(d.mean()), "max_mm": float(d.max()), "p95_mm": float(np.percentile(d, 95)),
            "n": int(len(d))}


class Judge:
    """The model of the project in `root` (after `dvc repro`), its nominal controller and the twin it was
    calibrated on; tcp: a `robot.tcp` name, the path that TCP's (the model, the controller's nominal
    kinematics and the twin's point judged all moved to it, lib/robot/tcp.py), else the marker's."""

    def __init__(self, params: dict, root=ROOT, tcp: str | None = None):
        self.params, self.robot = params, load_robot(params["robot"])
        self.cfg = params["compensate"]
        self.frame = read_json(root / FRAME_JSON)
        self.nominal_geometry = theory_geometry(self.robot, self.frame["tool_mm"])
        self.workspace = Workspace.from_dict(read_json(root / WORKSPACE_JSON))
        self.model = served(load_model(root / MODEL_WEIGHTS), self.workspace.network)
        self.offset = np.zeros(3)                                  # the point judged, in the probe's frame
        if tcp is not None:
            self.offset = probe_offsets(params["robot"]["tcp"], self.model.physics.geometry())[tcp]
            self.model, self.nominal_geometry = at_tcp(self.model, params["robot"]["tcp"], tcp, self.nominal_geometry)
        self.nominal = nominal_controller(self.nominal_geometry)
        self.twin = Twin.from_json(root / self.cfg["twin"])

    def truth(self, q_deg: np.ndarray) -> np.ndarray:
        """Where the twin's marker (or TCP: fixed to its probe) is at commanded joints, in the model's base
        frame (the fitted frame)."""
        if not self.offset.any():
            return to_base(self.twin.to_tracker(self.twin.expected_position(q_deg)), self.frame)
        p, R = self.twin.expected_pose(q_deg)
        return to_base(self.twin.to_tracker(p + R @ self.offset), self.frame)

    def along(self, segs, arc, q) -> dict:
        """The arm driven through joints q (k, 6) at arcs (k,): its deviation from segs along the path."""
        d = distance(self.truth(q), segs)
        return {**stats(d), "arc_mm": arc, "deviation_mm": d}

    def uncompensated(self, segs, q_start) -> tuple[dict, np.ndarray]:
        arc, q = controller_move(self.nominal, segs, q_start, self.cfg, self.robot)
        return self.along(segs, arc, q), q

    def waypoints(self, points, moves, segs, arc_nominal, q_nominal) -> dict:
        """The program's waypoints compensated (from their nominal IK joints), the controller's moves between
        the nominal positions of the compensated joints."""
        P = at(segs, arc_nominal)                                      # seeds: the nominal motion's nearest
        seeds = [q_nominal[np.argmin(np.linalg.norm(P - p, axis=1))] for p in points]
        q_wp = np.array([solve_path(self.nominal, p[None], [0.0], s, self.cfg, self.robot)[JCOMP_DEG].to_numpy()[0]
                         for p, s in zip(points, seeds)])
        df = pd.DataFrame(q_wp, columns=JOINTS_DEG).assign(**dict(zip(TARGET, points.T)))
        df.insert(0, "point_id", [f"W{i + 1}" for i in range(len(points))])
        table = compensate_program(df, self.model, self.workspace, self.robot, self.nominal_geometry, self.cfg)
        q_c = table[JCOMP_DEG].to_numpy()
        moved = segments(fk_numpy(q_c, self.robot, self.nominal_geometry), moves)
        arc, q = controller_move(self.nominal, moved, q_c[0], self.cfg, self.robot)
        return {**self.along(segs, arc, q), "waypoints": len(points),
                "waypoint_residual_mm_max": float(table.residual_mm.max())}

    def compensated(self, segs, q_start, spacing: float, chord: float | None = None) -> dict:
        targets, arc = resample(segs, spacing)
        t0 = time.perf_counter()
        table = solve_path(self.model, targets, arc, q_start, self.cfg, self.robot)
        if chord is not None:
            table = refine(self.model, table, segs, chord, self.cfg, self.robot)
        seconds = time.perf_counter() - t0
        if not table.converged.all() or len(table) < len(arc):
            raise RuntimeError(f"the compensated path did not converge at arc {table.arc_mm.iloc[-1]:.1f} mm")
        q, a = table[JCOMP_DEG].to_numpy(), table.arc_mm.to_numpy()
        at_samples = distance(self.truth(q), segs)
        inside = self.workspace(q)[1]
        out = self.along(segs, *joint_motion(a, q))
        return {**out, "samples": len(q), "at_samples": stats(at_samples), "in_workspace_share": float(inside.mean()),
                "model_step_middle_max_mm": float(deviation(model_position(self.model), q, segs, a, parts=2).max()),
                "solve_seconds": seconds}


def start_joints(judge: Judge, name: str, segs) -> np.ndarray:
    """PATHS' start joints; the side path's: the twin's side poses' nearest by nominal position."""
    q = PATHS[name][2]
    if q is not None:
        return np.asarray(q, float)
    poses = sample_poses(300, np.random.default_rng(5), judge.robot, region="side")
    p = fk_numpy(poses, judge.robot, judge.nominal_geometry)
    return poses[np.argmin(np.linalg.norm(p - PATHS[name][0][0], axis=1))]


def strip(r: dict) -> dict:
    return {k: v for k, v in r.items() if k not in ("arc_mm", "deviation_mm")}


def judge_path(judge: Judge, name: str, spacings, chord: bool = True) -> tuple[dict, dict]:
    """One path of PATHS judged: (its record, its curves for the figure)."""
    points, moves, _ = PATHS[name]
    segs = segments(points, moves)
    q0 = start_joints(judge, name, segs)
    t0 = time.perf_counter()
    unc, q_nominal = judge.uncompensated(segs, q0)
    arc_nominal = resample(segs, FINE_MM)[1]
    wp = judge.waypoints(points, moves, segs, arc_nominal, q_nominal)
    comp = {f"{s:g}": judge.compensated(segs, q_nominal[0], s) for s in spacings}
    curves = {"uncompensated": unc, "waypoints": wp, **{f"compensated {k} mm": comp[k] for k in ("1", "10") if k in comp}}
    out = {"length_mm": float(sum(s.length for s in segs)), "points": points.tolist(), "moves": moves,
           "start_deg": np.round(q0, 6).tolist(), "uncompensated": strip(unc), "waypoints": strip(wp),
           "compensated": {k: strip(v) for k, v in comp.items()}}
    if chord:
        out["chord"] = {"chord_mm": CHORD_MM, "from_spacing_mm": max(spacings),
                        **strip(judge.compensated(segs, q_nominal[0], max(spacings), CHORD_MM))}
    log.info("%s: uncompensated %.3f / %.3f mm, waypoints %.3f / %.3f, compensated 1 mm %s (mean / max)", name,
             unc["mean_mm"], unc["max_mm"], wp["mean_mm"], wp["max_mm"],
             f"{comp['1']['mean_mm']:.3f} / {comp['1']['max_mm']:.3f}" if "1" in comp else "-")
    return {**out, "seconds": time.perf_counter() - t0}, curves


def bench_path(spacings=SPACINGS, names=tuple(PATHS)) -> dict:
    """Every path, case and spacing judged on the twin; the goal's paths at 1 and 10 mm at each `robot.tcp`
    too (`at_tcp`); reports/bench/path.json and path_deviation.png."""
    params = load_params(ROOT / "params.yaml")
    judge = Judge(params)
    out = {"machine": machine(), "fine_mm": FINE_MM, "goals": GOALS, "paths": {}, "at_tcp": {}}
    curves = {}
    for name in names:
        out["paths"][name], curves[name] = judge_path(judge, name, spacings)
    for tcp in params["robot"]["tcp"] or {}:
        at = Judge(params, tcp=tcp)
        c = params["robot"]["tcp"][tcp]
        log.info("at the TCP %s (%s mm in the %s frame)", tcp, c["xyz_mm"], c.get("frame", "flange"))
        out["at_tcp"][tcp] = {"xyz_mm": params["robot"]["tcp"][tcp]["xyz_mm"], "paths": {
            n: judge_path(at, n, [s for s in spacings if s in (1.0, 10.0)], chord=False)[0]
            for n in GOALS["paths"] if n in names}}
    out["goals"]["met"] = {n: {"mean": out["paths"][n]["compensated"]["1"]["mean_mm"] <= GOALS["mean_mm"],
                               "max": out["paths"][n]["compensated"]["1"]["max_mm"] <= GOALS["max_mm"]}
                           for n in GOALS["paths"] if n in out["paths"] and "1" in out["paths"][n]["compensated"]}
    BENCH.mkdir(parents=True, exist_ok=True)
    write_json(BENCH / "path.json", out)
    save(figure(curves, out), BENCH / "path_deviation.png")
    return out


def figure(curves: dict, out: dict):
    """Deviation from the intended path along it, per path: uncompensated (the controller's nominal movel),
    its waypoints compensated, and every sample compensated at 1 and 10 mm; and how the compensated
    path's deviation grows with the spacing."""
    plt = _plt()
    fig, axes = plt.subplots(len(curves) + 1, 1, figsize=(9, 3.2 * (len(curves) + 1)))
    styles = {"uncompensated": ("0.5", "-"), "waypoints": ("tab:orange", "-"),
              "compensated 1 mm": ("tab:blue", "-"), "compensated 10 mm": ("tab:green", "--")}
    for ax, (name, cases) in zip(axes, curves.items()):
        for case, r in cases.items():
            c, ls = styles[case]
            ax.plot(r["arc_mm"], r["deviation_mm"], color=c, ls=ls, lw=1,
                    label=f"{case}: mean {r['mean_mm']:.3f}, max {r['max_mm']:.3f} mm")
        ax.set_yscale("log")
        ax.set_title(f"{name} ({out['paths'][name]['length_mm']:.0f} mm)")
        ax.set_xlabel("along the path, mm")
        ax.set_ylabel("deviation, mm")
        ax.legend(fontsize=7, loc="lower right")
    ax = axes[-1]
    for name in curves:
        comp = out["paths"][name]["compensated"]
        s = [float(k) for k in comp]
        ax.plot(s, [comp[k]["max_mm"] for k in comp], "o-", label=f"{name}: max")
        ax.plot(s, [comp[k]["mean_mm"] for k in comp], "o--", label=f"{name}: mean")
    ax.axhline(GOALS["max_mm"], color="k", lw=0.7, ls=":")
    ax.axhline(GOALS["mean_mm"], color="k", lw=0.7, ls=":")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("spacing of the compensated samples, mm")
    ax.set_ylabel("deviation, mm")
    ax.legend(fontsize=7, ncol=3)
    fig.tight_layout()
    return fig

"""Command: compensate a path, not only its waypoints: the TCP path resampled along its length, every
sample compensated, written as a CSV and a URScript that drives the compensated samples.

    python -m pipeline.commands.path PATH.csv --out DIR [--spacing MM | --chord MM] [--speed MM_S]
                            [--start-deg J1 .. J6] [--allow-outside-workspace] [--ignore-orientation]

PATH.csv, one row per waypoint (`,` `;` or tab separated, decimal point or comma; docs/robot-cell.md):
    target_x..z (base frame, mm)       the TCP's waypoints; without them, j1_deg..j6_deg (or j1_rad..,
                                       actual_q_0..: radians) and each waypoint is where the nominal
                                       kinematics puts its joints (an offline program)
    j1_deg..j6_deg (optional)          the joints; the first row's are the arm's at the path's start
                                       (without joint columns: --start-deg)
    move (optional; default movel)     how the path reaches the row from the one before: movel or movep (a
                                       straight line), via then movec (an arc through the via point); the
                                       first row is the start ("" or start)
    target_rx..rz (optional)           the orientation to hold (a rotation vector, rad, base frame) of the
                                       probe's frame (with --tcp, of the TCP's), slerped between waypoints
Writes DIR/path.csv (per sample: sample, arc_mm, t_s, target_x..z, j1_comp_deg..j6_comp_deg,
residual_mm, iterations, converged, in_workspace, uncertainty_mm, orientation_residual_arcsec) and
DIR/path.script (URScript: movej to the first sample, then a servoj every controller cycle, a CB3's 8 ms or
an e-Series' 2 ms (pathsolve.cycle_s), to where the path has reached then: at the speed, from rest to rest at
path.accel_mm_s2 and slower round corners, the whole path a whole number of cycles; pathsolve.schedule).

With an orientation (target_rx..rz, or for an offline path of joints the nominal flange orientation of
each waypoint's joints, as the program compensator's `compensate.orientation`), each sample is a pose:
six equations, position and the flange's orientation (a model calibrated with the probe's orientation;
target_rx..rz for one without are refused). --ignore-orientation compensates the position alone.

The path is resampled at most `path.spacing_mm` apart (--spacing), each step then halved while the model
puts its joint-space chord farther than `path.chord_mm` from the path (--chord); each sample is solved
from the previous sample's solution (lib/runtime/pathsolve.py). Safe by construction: only numbers formatted
here reach the script; a sample not reached, beyond the joint limits, a joint step faster than the joint's
speed limit at the path's speed, or a step whose joint-space chord leaves the path by more than
`path.max_deviation_mm` (a branch flip), sample 1 in another configuration than the start joints' (a
shoulder, elbow or wrist flipped, or a joint turned over 180°; for an offline path, any joint turned over
5°: waypoints.start_refusal), and a sample outside the trained workspace (unless
--allow-outside-workspace), refuse the path naming the sample (exit 1), and nothing is written; the
two files are written together, never over the input. Bad input exits 2 naming file, row and column.
Needs a finished `dvc repro` (model, workspace, frame).
"""
import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.lib.learning.checkpoint import load_model
from pipeline.lib.learning.model import served
from pipeline.lib.learning.workspace import Workspace
from pipeline.lib.project.artifacts import (FRAME_JSON, MODEL_WEIGHTS, PARAMS_FILE, WORKSPACE_JSON, project_owned,
                                            require)
from pipeline.lib.project.cli import Refused, add_project, one_line
from pipeline.lib.project.columns import JCOMP_DEG, TARGET
from pipeline.lib.project.config import for_stage, load_params, logger, read_json
from pipeline.lib.project.writing import check_outputs, csv_text, left_as_they_were, write_together
from pipeline.lib.robot.geometry import theory_geometry
from pipeline.lib.robot.kinematics import fk_numpy, nominal_geometry
from pipeline.lib.robot.robots import load_robot
from pipeline.lib.robot.tcp import at_tcp, in_flange
from pipeline.lib.robot.urdf import tcp_transforms
from pipeline.lib.runtime.compensation import reach_mm
from pipeline.lib.runtime.paths import n_samples, read_path, resample, rotations_at
from pipeline.lib.runtime.pathsolve import (Timing, beyond_reach, cycle_s, deviation, finish, joint_speeds,
                                            model_position, refine, refusal, schedule, solve_path, urscript)
from pipeline.lib.runtime.waypoints import flange_targets, start_refusal

log = logger(__name__)
PARAMS = ("robot", "compensate", "program", "path")
FILES = ("path.csv", "path.script")


def start_joints(found, start_deg, robot, src) -> np.ndarray:
    """The arm's joints at the path's start: the file's first row, or --start-deg (one of them)."""
    if found.joints_deg is not None and start_deg is not None:
        raise ValueError(f"{src}: the file gives the joints; leave out --start-deg")
    if found.joints_deg is None and start_deg is None:
        raise ValueError(f"{src}: no joint columns: give the arm's joints at the path's start with "
                         "--start-deg J1 .. J6 (degrees)")
    q = np.asarray(found.joints_deg[0] if start_deg is None else start_deg, float)
    beyond = robot.check_joints(q[None])[0]
    if beyond.any():
        j = int(np.flatnonzero(beyond)[0])
        raise ValueError(f"--start-deg: joint {j + 1} at {q[j]:g}° beyond its limits {robot.limits_deg[j].tolist()}°")
    return q


def summary_text(table: pd.DataFrame, dev: np.ndarray, spacing: float, speed: float) -> str:
    steps = np.diff(table.arc_mm.to_numpy())
    held = table.orientation_residual_arcsec.notna().any()
    orientation = f", the flange's orientation {table.orientation_residual_arcsec.max():.1e} arcsec" if held else ""
    return (f"{len(table)} samples over {table.arc_mm.iloc[-1]:.1f} mm (steps {steps.min():.3f}-{steps.max():.3f} "
            f"mm, spacing {spacing:g} mm): residual max {table.residual_mm.max():.1e} mm{orientation}; the joint-space steps "
            f"within {dev.max() if len(dev) else 0.0:.4f} mm of the path (the model, 7 points a step); "
            f"{int((~table.in_workspace).sum())} samples outside the trained workspace; "
            f"{table.t_s.iloc[-1]:.2f} s at {speed:g} mm/s")


def run(argv=None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(prog="python -m pipeline.commands.path", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("path", help="CSV: target_x..z and/or j1_deg..j6_deg, move (optional), one row per waypoint")
    ap.add_argument("--out", required=True, help="folder for path.csv and path.script (made if missing)")
    ap.add_argument("--spacing", type=float, default=None, help="samples at most this far apart, mm (path.spacing_mm)")
    ap.add_argument("--chord", type=float, default=None,
                    help="halve steps until the model puts each one's joint-space middle within this of the path, "
                         "mm (path.chord_mm)")
    ap.add_argument("--speed", type=float, default=None, help="TCP speed along the path, mm/s (path.speed_mm_s)")
    ap.add_argument("--start-deg", type=float, nargs=6, default=None, metavar="J",
                    help="the arm's joints at the path's start (deg), when the file has no joint columns")
    ap.add_argument("--allow-outside-workspace", action="store_true",
                    help="write a path with samples outside the trained workspace (flagged) instead of refusing it")
    ap.add_argument("--tcp", default=None, help="solve for this robot.tcp point (params.yaml) instead of the marker")
    ap.add_argument("--ignore-orientation", action="store_true",
                    help="compensate the position alone, leaving the orientation (target_rx..rz, or an offline "
                         "path's nominal one)")
    add_project(ap)
    a = ap.parse_args(argv)
    src, out, root = Path(a.path), Path(a.out), a.project
    check_outputs([out / f for f in FILES], [src], project_owned(root))   # a hard link to the input is the input
    earlier = left_as_they_were([out / f for f in FILES])
    p = for_stage(load_params(root / PARAMS_FILE), PARAMS)
    cfg = {**p["path"], **{k: v for k, v in (("spacing_mm", a.spacing), ("chord_mm", a.chord),
                                             ("speed_mm_s", a.speed)) if v is not None}}
    for key in ("spacing_mm", "chord_mm", "speed_mm_s"):
        if cfg[key] is not None and not (np.isfinite(cfg[key]) and cfg[key] > 0):
            raise ValueError(f"--{key.split('_')[0]}: expected a number > 0, got {cfg[key]}")
    tol = p["compensate"]["tol_mm"]
    if cfg["chord_mm"] is not None and cfg["chord_mm"] <= tol:    # a step's middle sits up to tol off anyway
        raise ValueError(f"--chord: {cfg['chord_mm']:g} mm is not above compensate.tol_mm ({tol:g} mm), to which "
                         "each sample is solved: no step could meet it")
    robot = load_robot(p["robot"])
    robot.check_joint_speed(p["program"]["movej"]["vel"], "program.movej.vel")     # the approach's movej
    speeds = joint_speeds(robot, cfg["joint_speed_deg_s"])
    require(root, (MODEL_WEIGHTS, WORKSPACE_JSON, FRAME_JSON))
    nominal = theory_geometry(robot, read_json(root / FRAME_JSON)["tool_mm"])
    workspace = Workspace.from_dict(read_json(root / WORKSPACE_JSON))
    model = served(load_model(root / MODEL_WEIGHTS), workspace.network)
    frame_rot = None                                 # target_rx..rz turn the probe's frame, or the TCP's
    if a.tcp is not None:
        at, nominal = at_tcp(model, p["robot"]["tcp"], a.tcp, nominal)     # refuses an unknown name
        frame_rot = tcp_transforms(in_flange(p["robot"]["tcp"], model.physics.geometry()))[a.tcp][:3, :3]
        model = at
    found = read_path(src, robot, lambda q: fk_numpy(q, robot, nominal))
    rotations = None                                 # arc_mm (k,) -> the flange's orientations (k, 3, 3)
    if not a.ignore_orientation:
        try:
            rots = flange_targets(model, p["compensate"], found.joints_deg, nominal, found.offline, found.rotvec,
                                  frame_rot)
        except Refused as e:
            raise Refused(f"{src}: {e}; rerun with --ignore-orientation to compensate the position alone; "
                          f"nothing written{earlier}") from None
        if rots is not None:
            rotations = lambda arc: rotations_at(found.segs, rots, arc)
    q0 = start_joints(found, a.start_deg, robot, src)
    n = n_samples(found.segs, cfg["spacing_mm"])
    if n > cfg["max_samples"]:
        length = sum(s.length for s in found.segs)
        raise ValueError(f"{src}: {n} samples at a spacing of {cfg['spacing_mm']:g} mm over {length:.1f} mm, more "
                         f"than path.max_samples ({cfg['max_samples']}): a larger --spacing")
    targets, arc = resample(found.segs, cfg["spacing_mm"])
    timing = Timing(cfg["speed_mm_s"], cfg["accel_mm_s2"], cfg["corner_mm"], cycle_s(robot))
    schedule(targets, arc, timing)                   # a ValueError where --speed is too low for URScript, or too high
    far = beyond_reach(targets, arc, reach_mm(model.physics.geometry()))
    if far:
        raise Refused(f"{src}: {far}; nothing written{earlier}")
    table = solve_path(model, targets, arc, q0, p["compensate"], robot,
                       None if rotations is None else rotations(arc))
    if cfg["chord_mm"] is not None and table.converged.all():
        table = refine(model, table, found.segs, cfg["chord_mm"], p["compensate"], robot, rotations,
                       cfg["max_samples"])
    timed = schedule(table[TARGET].to_numpy(), table.arc_mm.to_numpy(), timing)
    table = finish(table, workspace, timed)
    dev = deviation(model_position(model), table[JCOMP_DEG].to_numpy(), found.segs, table.arc_mm.to_numpy())
    why = refusal(table, n, robot.limits_deg, p["compensate"]["tol_mm"], dev, cfg["max_deviation_mm"],
                  timed.peak_mm_s, speeds, None if a.allow_outside_workspace else workspace)
    why = why or start_refusal(q0, table[JCOMP_DEG].to_numpy()[0], nominal_geometry(robot), found.offline,
                               orientation=rotations is not None)
    if why:
        raise Refused(f"{src}: {why}; nothing written{earlier}")
    out.mkdir(parents=True, exist_ok=True)
    approach = p["program"]["movej"]
    write_together({out / "path.csv": csv_text(table),
                    out / "path.script": urscript(table, timed, cfg["lookahead_s"], cfg["gain"],
                                                  approach["acc"], approach["vel"])}, [src])
    print(summary_text(table, dev, cfg["spacing_mm"], cfg["speed_mm_s"]))
    log.info("wrote %s and %s", out / "path.csv", out / "path.script")
    return table


def main(argv=None):
    return one_line("pipeline.commands.path", run, argv)


if __name__ == "__main__":
    main()

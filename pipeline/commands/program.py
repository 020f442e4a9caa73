"""Command: compensate a robot program: its waypoints in, the compensated program out (CSV and URScript).

    python -m pipeline.commands.program waypoints.csv [--out program_comp.csv] [--urscript program_comp.script]
                                             [--comment-out-unreached] [--tcp NAME]

waypoints.csv, one row per waypoint (`,` `;` or tab separated, decimal point or comma, as ingest reads):
    point_id (optional; default W001, W002, ...), j1_deg..j6_deg   the program's joint targets
    target_x..z (optional, base frame mm)                            the position to reach, the joints
                                                                     being where to start from
    target_rx..rz (optional, with target_x..z; rad)                  and the orientation: a rotation
                                                                     vector, base frame, of the probe's
                                                                     frame (with --tcp, of the TCP's)
Without target columns, a waypoint's target is where the nominal kinematics puts it
(nominal DH + the frame stage's tool: an offline-programmed point), and the
compensated joints make the trained model (the real arm) reach it: the position and, for a model
calibrated with orientation (`compensate.orientation`), the flange's orientation. Every waypoint
is solved by `compensate.solver` (lib/runtime/solvers.py) within the joint limits; the output CSV
is the Δθ table (docs/data-format.md), the URScript one `movej` per waypoint.

The waypoints are read, checked and compensated by lib/runtime/waypoints.py (shared with `python -m pipeline.commands.plan`).
Safe by construction (docs/robot-cell.md):
  - nothing from the file reaches the URScript but numbers formatted here and point ids that
    match ID_PATTERN (others are refused with file, row and column);
  - a waypoint that did not converge, whose answer lies outside the joint limits, or whose answer is
    not a compensation of its joints (offline: a joint turned over 5°; with targets: another
    configuration than the given joints', a shoulder, elbow or wrist flipped or a joint turned over
    180°: waypoints.unreached) never becomes a move: the program is refused (exit 1, those waypoints
    listed, nothing written; an earlier run's files at the output paths are named, left as they were), or, with
    --comment-out-unreached, written with each such waypoint as a comment and no move;
  - with program.move movel, a move between two waypoints in different configurations (a shoulder,
    elbow or wrist across its singularity: waypoints.linear_flips) refuses the program;
  - angles that look like radians in the *_deg columns are refused, as ingest refuses them;
  - waypoints outside the trained workspace are listed in the summary printed at the end;
  - the CSV and the URScript are written together or not at all, never over the input (whatever the
    path's spelling: a hard or symbolic link to it is refused).
Bad input exits 2 with the file, row (the header is row 1) and column. Needs a finished
`dvc repro` (model, workspace, frame).
"""
import argparse
from pathlib import Path

import numpy as np
import pandas as pd
import torch

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
from pipeline.lib.robot.robots import load_robot
from pipeline.lib.robot.tcp import at_tcp, in_flange
from pipeline.lib.robot.urdf import tcp_transforms
from pipeline.lib.runtime.waypoints import (ID_PATTERN, as_written, compensate_program, linear_flips, read_waypoints,
                                           unreached)

log = logger(__name__)
PARAMS = ("robot", "compensate", "program")


MOVES = {"movej": "rad/s^2, rad/s", "movel": "m/s^2, m/s"}   # program.move: the units of its acc, vel (ASCII)


def ascii_text(text: str) -> str:
    """A comment's words for the script in ASCII (a controller's reader need not take UTF-8): ° as deg."""
    return text.replace("°", " deg").replace("″", " arcsec").encode("ascii", "replace").decode()


def urscript(table: pd.DataFrame, skipped: dict, move: str = "movej", acc: float = 1.4, vel: float = 1.05) -> str:
    """A URScript program: one `move` (movej: joint interpolation; movel: the TCP on a straight line) per
    reached waypoint to its compensated joints (rad), at acc, vel (MOVES' units). Only numbers formatted
    here and validated ids reach it; a `skipped` waypoint is a comment, never a move."""
    if move not in MOVES:
        raise ValueError(f"params.yaml program.move: one of {sorted(MOVES)}, got {move!r}")
    lines = [f"# compensated by `python -m pipeline.commands.program`: {len(table)} waypoints, {len(skipped)} not reached "
             f"(commented out, no move); {move}, acc and vel in {MOVES[move]}",
             "def compensated_program():", f"  acc = {float(acc):.6f}", f"  vel = {float(vel):.6f}"]
    q_rad = np.radians(table[JCOMP_DEG].to_numpy(float)).tolist()          # (n, 6), one call for the program
    for pid, q, inside, u, res, ores in zip(table.point_id, q_rad, table.in_workspace, table.uncertainty_mm,
                                            table.residual_mm, table.orientation_residual_arcsec):
        pid = pid if ID_PATTERN.fullmatch(str(pid)) else "?"                  # read_waypoints refused others
        if pid in skipped or pid == "?":
            lines.append(f"  # {pid}: NOT REACHED ({ascii_text(skipped.get(pid, 'invalid id'))}): no move")
            continue
        q = ", ".join(f"{v:.9f}" for v in q)
        flag = "" if inside else f", outside the trained workspace (uncertainty {u:.3f} mm)"
        orient = f", orientation {float(ores):.2f} arcsec" if np.isfinite(ores) else ""
        lines += [f"  # {pid}: residual {res:.4f} mm{orient}{flag}", f"  {move}([{q}], a=acc, v=vel)"]
    return "\n".join(lines + ["end", ""])


def summary_text(table: pd.DataFrame, skipped: dict, workspace) -> str:
    """What a person reads at the end: counts, the waypoints not reached, those outside the workspace."""
    reached = table.residual_mm[~table.point_id.isin(list(skipped))]
    worst = f" (residual max {reached.max():.2e} mm)" if len(reached) else ""
    out = [f"{len(table)} waypoints: {len(reached)} reached{worst}, {len(skipped)} not reached"]
    out += [f"  NOT REACHED {p}: {why}" for p, why in skipped.items()]
    outside = table[~table.in_workspace]
    if len(outside):
        d = workspace.distance(outside[JCOMP_DEG].to_numpy()) / workspace.radius
        out.append(f"{len(outside)} waypoint(s) outside the trained workspace (the correction fades there; "
                   "measure poses near them to cover them):")
        out += [f"  {p}: {x:.1f} workspace radii from the nearest training pose, uncertainty {u:.3f} mm"
                for p, x, u in zip(outside.point_id, d, outside.uncertainty_mm)]
    return "\n".join(out)


def run(argv=None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(prog="python -m pipeline.commands.program", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("waypoints", help="CSV: point_id (optional), j1_deg..j6_deg, target_x..z (optional)")
    ap.add_argument("--out", help="compensated CSV (default <waypoints>_comp.csv)")
    ap.add_argument("--urscript", help="URScript file (default <waypoints>_comp.script)")
    ap.add_argument("--comment-out-unreached", action="store_true",
                    help="write the program with every waypoint not reached as a comment (no move) "
                         "instead of refusing it")
    ap.add_argument("--tcp", default=None, help="compensate for this robot.tcp point (params.yaml), not the marker")
    add_project(ap)
    a = ap.parse_args(argv)
    root = a.project
    src = Path(a.waypoints)
    out = Path(a.out or src.with_name(src.stem + "_comp.csv"))
    script = Path(a.urscript or src.with_name(src.stem + "_comp.script"))
    inputs = [src, root / PARAMS_FILE, root / MODEL_WEIGHTS, root / WORKSPACE_JSON, root / FRAME_JSON]
    check_outputs([out, script], inputs, project_owned(root))   # by inode too: a hard link to an input is the input
    for f in (out, script):                          # said before solving, not after
        if not f.parent.is_dir():
            raise ValueError(f"{f}: its folder {f.parent} does not exist; nothing written")
    p = for_stage(load_params(root / PARAMS_FILE), PARAMS)
    robot = load_robot(p["robot"])
    if p["program"]["move"] == "movej":
        robot.check_joint_speed(p["program"]["movej"]["vel"], "program.movej.vel")
    require(root, (MODEL_WEIGHTS, WORKSPACE_JSON, FRAME_JSON))
    df = read_waypoints(src, robot)
    workspace = Workspace.from_dict(read_json(root / WORKSPACE_JSON))
    model = served(load_model(root / MODEL_WEIGHTS), workspace.network)
    nominal = theory_geometry(robot, read_json(root / FRAME_JSON)["tool_mm"])
    frame_rot = None                                 # target_rx..rz turn the probe's frame, or the TCP's
    if a.tcp is not None:                            # targets and solve at a TCP (lib/robot/tcp.py)
        at, nominal = at_tcp(model, p["robot"]["tcp"], a.tcp, nominal)     # refuses an unknown name
        frame_rot = tcp_transforms(in_flange(p["robot"]["tcp"], model.physics.geometry()))[a.tcp][:3, :3]
        model = at
    try:
        table = compensate_program(df, model, workspace, robot, nominal, p["compensate"], frame_rot)
    except Refused as e:                             # beyond the reach, orientation without a model for it
        raise Refused(f"{src}: {e}; nothing written{left_as_they_were([out, script])}") from None
    skipped = unreached(table, robot, offline=TARGET[0] not in df)     # offline: Δθ a compensation, bounded
    text = summary_text(table, skipped, workspace)
    if skipped and not a.comment_out_unreached:
        raise Refused(f"{src}: {len(skipped)} waypoint(s) not reached; nothing written (or rerun with "
                      f"--comment-out-unreached to write them as comments, no move){left_as_they_were([out, script])}"
                      f"\n{text}")
    c = p["program"]
    flips = linear_flips(table, skipped, model.physics.geometry()) if c["move"] == "movel" else []
    if flips:
        raise Refused(f"{src}: program.move is movel, and {len(flips)} move(s) would take the arm through a "
                      f"singularity on a straight line: {'; '.join(flips)}; nothing written (program.move: movej moves "
                      f"joint by joint; or teach the waypoint again in the configuration of the one before)"
                      f"{left_as_they_were([out, script])}")
    write_together({out: csv_text(as_written(table, skipped)),
                    script: urscript(table, skipped, c["move"], **c[c["move"]])}, inputs)
    print(text)
    log.info("wrote %s and %s", out, script)
    return table


def main(argv=None):
    torch.set_num_threads(1)          # the process's: a long program's blocks then run on every core (solvers.in_blocks)
    return one_line("pipeline.commands.program", run, argv)


if __name__ == "__main__":
    main()

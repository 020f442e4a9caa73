"""A robot program's waypoints (docs/robot-cell.md): read and checked by one set of rules, and compensated,
for the program compensator (`python -m pipeline.commands.program`), the measurement planner (`python -m
pipeline.commands.plan`) and the benchmarks.

    read_waypoints(path, robot)      point_id, j1_deg..j6_deg (or j1_rad.., actual_q_0..: radians) and, if
                                     given, target_x..z and target_rx..rz; bad input is an
                                     IngestError naming file, row (the header is row 1) and column: a
                                     row whose cell count does not fit the header (ingest's field_count
                                     rule, readers.shape_problems), a bad number, a duplicate id
    compensate_program(df, ...)      the Δθ table of the waypoints (compensation.delta_table)
    unreached(table, robot, offline) the waypoints that must not become moves, and why (offline: a Δθ over
                                     MAX_COMPENSATION_DEG too; with targets: an answer in another
                                     configuration than its joints', another_configuration)
    ID_PATTERN                       what a point id may be: it reaches a URScript comment
"""
import re

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from pipeline.lib.project.cli import Refused
from pipeline.lib.project.columns import DJ_DEG, JCOMP_DEG, JOINTS_DEG, TARGET
from pipeline.lib.project.config import logger
from pipeline.lib.reading.readers import (AUTO_JOINTS, IngestError, find_column, headers_found,
                                          looks_like_radians, parse_number, parse_column, read_table,
                                          shape_problems, unit_of)
from pipeline.lib.robot.kinematics import TOOL_ROT, fk_numpy, nominal_geometry, tool_rotation
from pipeline.lib.robot.poses import CONFIGURATION, configuration_margin
from pipeline.lib.runtime.compensation import (delta_table, nominal_flange, orientation_targets, reach_mm,
                                               solve)
from pipeline.lib.runtime.paths import ROTVEC, check_rotvecs, check_unused

log = logger(__name__)
METRES_MM = 5.0                 # a target not reached nearer the base origin than this was likely given in metres
ID_PATTERN = re.compile(r"[A-Za-z0-9_.:-]{1,64}")          # what a point id may be, to reach a URScript comment
MAX_COMPENSATION_DEG = 5.0      # an offline waypoint's Δθ on any joint: the twin's campaign-like poses need ≤ 1.5°;
                                # beyond, the answer is another configuration (near a singularity: joint 5 near 0°
                                # or 180° turns joints 2-4 and 6 by tens of degrees), not a correction


def too_far(q0_deg: np.ndarray, q_deg: np.ndarray, max_deg: float = MAX_COMPENSATION_DEG) -> list:
    """Per row of joints q0 (n, 6) deg and their compensated q (n, 6): why the answer is not a compensation of
    q0 (a joint turned more than max_deg), or None."""
    d = np.abs(np.asarray(q_deg, float) - np.asarray(q0_deg, float))
    return [None if not (row.max() > max_deg) else
            f"joint {int(row.argmax()) + 1} turned {row.max():.1f}° from the programmed joints (more than "
            f"{max_deg:g}°: another configuration, not a compensation; joint 5 at {q[4]:.2f}°: near the wrist's "
            "singularity?)" for row, q in zip(d, np.asarray(q0_deg, float))]


def another_configuration(q0_deg: np.ndarray, q_deg: np.ndarray, geometry: dict, orientation=True,
                          than: str = "the given joints'", advice: str = "give joints nearer the target") -> list:
    """Per row of joints q0 (n, 6) deg and the answer q (n, 6) solved from them for an explicit target: why q is
    not in q0's configuration, or None. Another configuration: a joint turned more than 180° (the same angle
    lies nearer the other way round), or, with a joint turned more than MAX_COMPENSATION_DEG, a shoulder, elbow
    or wrist on the other side of its singularity (poses.configuration_margin) than q0, where q0 lies at least
    5° from it (nearer, as UR's home with q3 = q5 = 0, it is on neither side). The wrist counts only where the
    target has an orientation (orientation: a bool, or one per row; without one, the flange's orientation,
    which sets the wrist's side, is free). than, advice: what q0 is and what to do, in the message."""
    q0, q = np.atleast_2d(np.asarray(q0_deg, float)), np.atleast_2d(np.asarray(q_deg, float))
    d = np.abs(q - q0)
    out = [None] * len(q)
    far = np.flatnonzero(d.max(1) > MAX_COMPENSATION_DEG)           # within it: no flip that swings anything
    if not len(far):
        return out
    m0, m = configuration_margin(q0[far], geometry), configuration_margin(q[far], geometry)    # (len(far), 3)
    flipped = (m0 * m < 0) & (np.abs(m0) > np.sin(np.radians(MAX_COMPENSATION_DEG)))  # q0 at a singularity
    # (within 5° of it: UR's home, q3 = q5 = 0, the wrist centre over the base axis) is in neither configuration
    flipped[:, CONFIGURATION.index("wrist")] &= np.broadcast_to(np.asarray(orientation, bool), (len(q),))[far]
    for k, f in zip(far, flipped):
        row, j = d[k], int(d[k].argmax())
        why = [f"the {CONFIGURATION[c]} flipped" for c in np.flatnonzero(f)]
        why += [f"joint {j + 1} turned {row[j]:.1f}° (the same angle lies {360.0 - row[j]:.1f}° the other way "
                "round)"] if row[j] > 180.0 else []
        if why:
            out[k] = (f"another configuration than {than}: {', '.join(why)} (joint {j + 1} turned {row[j]:.1f}°, "
                      f"joint 5 {q0[k, 4]:.1f}° -> {q[k, 4]:.1f}°): {advice}")
    return out


def start_refusal(q0_deg: np.ndarray, first_deg: np.ndarray, geometry: dict, offline: bool,
                  orientation: bool) -> str | None:
    """Why a path's sample 1, solved from the start joints q0 (6,) deg to first (6,) deg, must not be driven
    to, or None: offline (the start's own nominal pose), a Δθ over MAX_COMPENSATION_DEG (too_far); else
    another configuration than the start's (another_configuration; orientation: the path holds one)."""
    q0, first = np.asarray(q0_deg, float)[None], np.asarray(first_deg, float)[None]
    why = (too_far(q0, first) if offline else another_configuration(q0, first, geometry, orientation))[0]
    return None if why is None else f"sample 1 (arc 0.0 mm): {why}"


def joint_columns(header: list, path) -> tuple[list, list]:
    """The six joint columns' indices and units: j1_deg..j6_deg (degrees), j1_rad..j6_rad or actual_q_0..5
    (radians, as ingest reads them and a UR controller logs them); else an IngestError."""
    have = {h.lower() for h in header}
    for names in AUTO_JOINTS[:3]:
        if all(n in have for n in names):
            return [find_column(header, n, "waypoint", str(path)) for n in names], [unit_of(n, "deg") for n in names]
    missing = next(n for n in JOINTS_DEG if n not in have)
    raise IngestError(f"missing waypoint column '{missing}' (or j1_rad..j6_rad, or actual_q_0..actual_q_5 in "
                      f"radians); {headers_found(header)}", file=path, column=missing)


def numbers(cells: list, cols: list, names: list, decimal: str, path, lines: list) -> np.ndarray:
    """The cells of columns `cols` as numbers (rows, len(cols)): a column at a time (readers.parse_column),
    else cell by cell to name the first bad cell (an IngestError: file, row, column)."""
    fast = [parse_column([row[c] for row in cells], decimal) for c in cols]   # shape_problems: every row has c
    if all(v is not None for v in fast):
        return np.stack(fast, 1)
    values = np.empty((len(cells), len(cols)))
    for r, row in enumerate(cells):
        for k, c in enumerate(cols):
            values[r, k], err = parse_number(row[c], decimal)
            if err or not np.isfinite(values[r, k]):
                raise IngestError(f"not a finite number ({err[1] if err else row[c]})", file=path, row=lines[r],
                                  column=names[k])
    return values


def read_waypoints(path, robot) -> pd.DataFrame:
    """The waypoints file, checked: point_id, the joints (degrees, or radians by their names) and, if given,
    target_x..z; every bad cell is an IngestError naming file, row (the header is row 1) and column."""
    header, cells, lines, _, decimal = read_table(str(path), "auto", "auto")
    lower = {h.lower() for h in header}
    targets = [c for c in TARGET if c in lower]
    if 0 < len(targets) < 3:
        raise IngestError(f"target columns need all of {TARGET}; found {targets}", file=path)
    turned = [c for c in ROTVEC if c in lower]
    if turned and (len(turned) < 3 or not targets):
        raise IngestError(f"an orientation needs all of {ROTVEC} and a position, {TARGET}; found "
                          f"{targets + turned}", file=path)
    jcols, units = joint_columns(header, path)
    given = (TARGET if targets else []) + (ROTVEC if turned else [])
    cols = jcols + [find_column(header, c, "waypoint", str(path)) for c in given]
    names = [header[c] for c in cols]
    check_unused(header, set(cols) | {c for c, h in enumerate(header) if h.strip().lower() == "point_id"}, path,
                 f"point_id, {JOINTS_DEG[0]}..{JOINTS_DEG[-1]} (or *_rad, actual_q_*), {', '.join(TARGET)} and "
                 f"{', '.join(ROTVEC)}")
    for r, problem in enumerate(shape_problems(cells, header)):
        if problem:                                  # its cells would be read shifted: a wrong move
            raise IngestError(problem, file=path, row=lines[r])
    values = numbers(cells, cols, names, decimal, path, lines)
    values[:, :6] = np.where(np.array(units) == "rad", np.degrees(values[:, :6]), values[:, :6])
    df = pd.DataFrame(values, columns=JOINTS_DEG + given)
    if turned:
        check_rotvecs(df[ROTVEC].to_numpy(), path, lines)
    if "point_id" in lower:
        c = find_column(header, "point_id", "point id", str(path))
        ids = [row[c].strip() if c < len(row) else "" for row in cells]
        for r, pid in enumerate(ids):
            if not ID_PATTERN.fullmatch(pid):
                raise IngestError(f"point id {pid[:40]!r} is not 1-64 of the characters A-Z a-z 0-9 _ . : - "
                                  "(ids reach the robot program's comments)", file=path, row=lines[r],
                                  column=header[c])
        first = {}
        for r, pid in enumerate(ids):
            if first.setdefault(pid, r) != r:        # each waypoint's answer is keyed by its id
                raise IngestError(f"point id {pid!r} already on row {lines[first[pid]]}", file=path,
                                  row=lines[r], column=header[c])
    else:
        ids = [f"W{i + 1:03d}" for i in range(len(df))]
    df.insert(0, "point_id", ids)
    out = robot.check_joints(df[JOINTS_DEG].to_numpy())
    if out.any():
        i, j = map(int, np.argwhere(out)[0])
        lo, hi = robot.limits_deg[j]
        raise IngestError(f"{df[JOINTS_DEG[j]].iloc[i]}° beyond the joint limits [{lo:g}, {hi:g}]°", file=path,
                          row=lines[i], column=header[jcols[j]])
    if units[0] == "deg" and looks_like_radians(df[JOINTS_DEG].to_numpy()):
        raise IngestError("every joint angle lies within ±6.29: these look like radians in *_deg columns; "
                          "convert them to degrees", file=path)
    return df


def flange_targets(model, cfg: dict, q0_deg: np.ndarray, nominal: dict, offline: bool, rotvec=None,
                   frame_rot=None) -> np.ndarray | None:
    """The flange's orientation targets (n, 3, 3), base frame, of n waypoints, or None (position only):
    rotvec (n, 3), rotation vectors (rad, base frame) of a frame whose rotation in the flange is frame_rot
    (3, 3) (None: the probe's, the model's tool_rot); else, for offline-programmed waypoints (offline) with
    `compensation.orientation_targets`, the nominal flange of their joints q0_deg (n, 6). A rotvec for a
    model calibrated without orientation is refused (Refused)."""
    if rotvec is None:
        return nominal_flange(q0_deg, nominal) if offline and orientation_targets(model, cfg) else None
    g = model.physics.geometry()
    if TOOL_ROT not in g:
        raise Refused(f"columns {', '.join(ROTVEC)}: the model was calibrated without the probe's orientation, "
                      "so an orientation cannot be compensated; leave them out, or calibrate on a campaign "
                      "with orientation")
    frame_rot = tool_rotation(g).numpy() if frame_rot is None else np.asarray(frame_rot, float)
    return Rotation.from_rotvec(np.asarray(rotvec, float)).as_matrix() @ frame_rot.T   # (n, 3, 3)


def compensate_program(df: pd.DataFrame, model, workspace, robot, nominal: dict, cfg: dict,
                       frame_rot: np.ndarray | None = None) -> pd.DataFrame:
    """The Δθ table of the waypoints df (targets: df's, else the nominal poses of its joints: their positions
    and, with `compensation.orientation_targets`, the flange's orientations). df's target_rx..rz turn the
    target's frame, whose rotation in the flange is frame_rot (3, 3) (None: the probe's, the model's
    tool_rot); refused (Refused) for a model calibrated without orientation."""
    q0 = df[JOINTS_DEG].to_numpy()
    offline = TARGET[0] not in df
    target = fk_numpy(q0, robot, nominal) if offline else df[TARGET].to_numpy()
    flange_rot = flange_targets(model, cfg, q0, nominal, offline,
                                df[ROTVEC].to_numpy(float, copy=True) if ROTVEC[0] in df else None, frame_rot)
    reach = reach_mm(model.physics.geometry())
    far = np.linalg.norm(target, axis=1) > reach
    if far.any():
        raise Refused("unreachable: " + "; ".join(
            f"{p}: target {np.linalg.norm(t):.1f} mm from the base, beyond the arm's reach of {reach:.1f} mm"
            for p, t in zip(df.point_id[far], target[far])))
    solved = solve(model, q0, target, cfg, robot, history=False, flange_rot=flange_rot)
    table = delta_table(df["point_id"], q0, target, solved, workspace)
    log.info("%d waypoints compensated in %.2f s (%s): %d converged (residual max %.2e mm), %d outside the "
             "trained workspace", len(table), solved.seconds, "position only" if flange_rot is None else
             "position and orientation", table.converged.sum(), table.residual_mm.max(), (~table.in_workspace).sum())
    return table


def linear_flips(table: pd.DataFrame, skipped: dict, geometry: dict) -> list[str]:
    """The moves a `movel` program cannot make: from each waypoint written as a move to the next, a shoulder,
    elbow or wrist on the other side of its singularity (poses.configuration_margin of the compensated joints
    JCOMP_DEG): a straight line between them passes through that singularity. Said per move, in order."""
    moved = table[~table.point_id.isin(list(skipped))]
    if len(moved) < 2:
        return []
    m = configuration_margin(moved[JCOMP_DEG].to_numpy(), geometry)                  # (n, 3)
    ids = moved.point_id.tolist()
    return [f"{ids[k]} -> {ids[k + 1]}: the {' and the '.join(CONFIGURATION[c] for c in np.flatnonzero(f))} on the "
            "other side of its singularity" for k, f in enumerate(m[:-1] * m[1:] < 0) if f.any()]


def unreached(table: pd.DataFrame, robot, offline: bool = False) -> dict:
    """{point_id: why} for every waypoint that must not become a move; offline (the targets are the nominal
    poses of the waypoints' joints): also an answer that turned a joint more than MAX_COMPENSATION_DEG; with
    explicit targets: also an answer in another configuration than its joints' (another_configuration)."""
    q0, q = table[JOINTS_DEG].to_numpy(), table[JCOMP_DEG].to_numpy()
    beyond = robot.check_joints(q).any(1)
    posed = np.isfinite(table.orientation_residual_arcsec.to_numpy(float))     # solved with an orientation
    far = too_far(q0, q) if offline else another_configuration(q0, q, nominal_geometry(robot), posed)
    return {r.point_id: (f"residual {r.residual_mm:.4f} mm"
                         + (f", orientation {r.orientation_residual_arcsec:.2f} arcsec"
                            if np.isfinite(r.orientation_residual_arcsec) else "")
                         + (", not converged" if not r.converged else "")
                         + (", beyond the joint limits" if b else "") + (f", {f}" if f else ""))
            + (", a target this close to the base looks like metres: target_x..z are in millimetres"
               if np.linalg.norm([r.target_x, r.target_y, r.target_z]) < METRES_MM and not r.converged else "")
            for r, b, f in zip(table.itertuples(), beyond, far) if not r.converged or b or f}


def as_written(table: pd.DataFrame, skipped: dict) -> pd.DataFrame:
    """A Δθ table as written for a robot cell (the program command's compensated CSV, `compensate --targets`): a
    target not reached (`unreached`) has no angles to command (j*_comp_deg and dj*_deg empty) and says why in
    `not_reached` (empty where it was reached)."""
    out = table.copy()
    gone = out.point_id.isin(list(skipped)).to_numpy()
    out.loc[gone, DJ_DEG + JCOMP_DEG] = np.nan
    out["not_reached"] = [skipped.get(pid, "") for pid in out.point_id]
    return out

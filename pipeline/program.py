"""Compensate a robot program: its waypoints in, the compensated program out (CSV and URScript).

    python -m pipeline.program waypoints.csv [--out program_comp.csv] [--urscript program_comp.script]

waypoints.csv, one row per waypoint:
    point_id (optional; default W001, W002, ...), j1_deg..j6_deg   the program's joint targets
    target_x..z (optional, base frame mm)                            the position to reach, the joints
                                                                     being where to start from
Without target columns, a waypoint's target is where the nominal kinematics puts it
(nominal DH + the frame stage's tool: an offline-programmed point), and the
compensated joints make the trained model (the real arm) reach it. Every waypoint
is solved by `compensate.solver` (lib/solvers.py) with joint limits; the output CSV
has the Δθ table's columns (DATA_FORMAT.md), so residual_mm, converged and
in_workspace flag each waypoint, and the URScript has one `movej` per waypoint,
flagged in a comment where it did not converge or leaves the trained workspace.
Needs a finished `dvc repro` (model, workspace, frame).
"""
import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from .lib.artifacts import WORKSPACE_JSON
from .lib.columns import COMPENSATION, DJ_DEG, JCOMP_DEG, JOINTS_DEG, PRED, TARGET
from .lib.config import load_params, logger, read_json, section, sections
from .lib.geometry import theory_geometry
from .lib.kinematics import fk_numpy
from .lib.robots import load_robot
from .lib.solvers import compensate
from .lib.training import load_model
from .lib.workspace import Workspace

log = logger(__name__)


def read_waypoints(path, robot) -> pd.DataFrame:
    """The waypoints CSV, checked: every bad cell named by file, row (as a spreadsheet numbers it:
    the header is row 1) and column."""
    df = pd.read_csv(path)
    missing = [c for c in JOINTS_DEG if c not in df.columns]
    if missing:
        raise ValueError(f"{path}: missing column(s) {missing}; found {list(df.columns)}")
    cols = JOINTS_DEG + [c for c in TARGET if c in df.columns]
    if 0 < len(cols) - 6 < 3:
        raise ValueError(f"{path}: target columns need all of {TARGET}; found {cols[6:]}")
    for c in cols:
        num = pd.to_numeric(df[c], errors="coerce")
        bad = ~np.isfinite(num.to_numpy(float))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"{path}: row {i + 2}, column {c}: not a finite number ({df[c].iloc[i]!r})")
        df[c] = num
    out = robot.check_joints(df[JOINTS_DEG].to_numpy())
    if out.any():
        i, j = map(int, np.argwhere(out)[0])
        lo, hi = robot.limits_deg[j]
        raise ValueError(f"{path}: row {i + 2}, column {JOINTS_DEG[j]}: {df[JOINTS_DEG[j]].iloc[i]}° "
                         f"beyond the joint limits [{lo:g}, {hi:g}]°")
    if "point_id" not in df.columns:
        df.insert(0, "point_id", [f"W{i + 1:03d}" for i in range(len(df))])
    return df


def compensate_program(params: dict, df: pd.DataFrame) -> pd.DataFrame:
    """The Δθ table (columns COMPENSATION) of the waypoints df."""
    cfg, robot = section(params, "compensate"), load_robot(section(params, "robot"))
    q0 = df[JOINTS_DEG].to_numpy()
    if all(c in df.columns for c in TARGET):
        target = df[TARGET].to_numpy()
    else:
        target = fk_numpy(q0, *theory_geometry(params))                    # where the program meant to go
    q, pred, iters, ok, _, sec = compensate(load_model(params), q0, target, cfg, robot)
    out = df[["point_id"] + JOINTS_DEG].copy()
    out[DJ_DEG], out[JCOMP_DEG] = q - q0, q
    out[TARGET], out[PRED] = target, pred
    out["residual_mm"], out["iterations"], out["converged"] = np.linalg.norm(pred - target, axis=1), iters, ok
    out["uncertainty_mm"], out["in_workspace"] = Workspace.from_dict(read_json(WORKSPACE_JSON))(q)
    log.info("%d waypoints compensated in %.2f s: %d converged (residual max %.2e mm), %d outside the "
             "trained workspace", len(out), sec, ok.sum(), out["residual_mm"].max(), (~out["in_workspace"]).sum())
    return out[COMPENSATION]


def urscript(table: pd.DataFrame, source: str, acc: float = 1.4, vel: float = 1.05) -> str:
    """A URScript program: one movej per waypoint to its compensated joints (rad)."""
    lines = [f"# compensated by `python -m pipeline.program {source}`: {len(table)} waypoints",
             "def compensated_program():",
             f"  acc = {acc}", f"  vel = {vel}"]
    for _, r in table.iterrows():
        q = ", ".join(f"{v:.9f}" for v in np.radians(r[JCOMP_DEG].to_numpy(float)))
        flags = [f"residual {r['residual_mm']:.4f} mm"] + (["NOT CONVERGED"] if not r["converged"] else []) \
            + (["outside the trained workspace"] if not r["in_workspace"] else [])
        lines += [f"  # {r['point_id']}: {', '.join(flags)}", f"  movej([{q}], a=acc, v=vel)"]
    return "\n".join(lines + ["end", ""])


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m pipeline.program", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("waypoints", help="CSV: point_id (optional), j1_deg..j6_deg, target_x..z (optional)")
    ap.add_argument("--out", help="compensated CSV (default <waypoints>_comp.csv)")
    ap.add_argument("--urscript", help="URScript file (default <waypoints>_comp.script)")
    a = ap.parse_args(argv)
    params = load_params()
    sections(params, "model", "train")                                    # load_model reads them
    src = Path(a.waypoints)
    table = compensate_program(params, read_waypoints(src, load_robot(section(params, "robot"))))
    out = Path(a.out or src.with_name(src.stem + "_comp.csv"))
    script = Path(a.urscript or src.with_name(src.stem + "_comp.script"))
    table.to_csv(out, index=False, float_format="%.6f")
    script.write_text(urscript(table, src.name))
    log.info("wrote %s and %s", out, script)
    return table


if __name__ == "__main__":
    main()

"""Stage compensate: Δθ tables by inverting the frozen model (sec. 2.3, eq. 19).

Targets are the test points' theory positions, started from their recorded
angles (as in the paper). The Δθ table (docs/data-format.md) comes from
`compensate.solver`; both solvers (lib/runtime/solvers.py) run and their convergence is
recorded, and so is the controller path (lib/runtime/realtime.py: one pose per call,
two model evaluations) on the same targets. With `compensate.drive_check` the
twin (`compensate.twin`) is driven to the recorded and to the compensated
angles and measured (the paper's Table 9) and, for every `robot.tcp` where the campaign measures
orientation, the TCP's nominal positions at the test poses are solved for (lib/robot/tcp.py AtTcp) and the
twin driven there and measured through its probe's pose (compensation.json `tcp_drive_check`), when
the campaign is the twin's own
(its files' SHA-256 in reports/ingest.json are those twin.json records); on any
other campaign (a real robot) compensation.json says why there is none. The
model solved is the one served (model.served: the physics alone where evaluate
switched the network off).

Your own targets, outside DVC: `python -m pipeline.stages.compensate --targets my.csv`
(columns point_id, j1_deg..j6_deg, target_x..z in the base frame and, optionally, target_rx..rz: the
probe frame's orientation, a rotation vector in rad, as the program command reads them; read and checked
by lib/runtime/waypoints.py, a bad cell naming file, row and column) writes
reports/compensation_<name>.csv.
"""
import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.lib.learning.checkpoint import load_model
from pipeline.lib.learning.metrics import stats
from pipeline.lib.learning.model import served
from pipeline.lib.learning.workspace import Workspace
from pipeline.lib.project.artifacts import (COMPENSATION_CSV, COMPENSATION_JSON, COMPENSATION_PARQUET,
                                            CONVERGENCE_CSV, DRIVE_CSV, HERE, INGEST_JSON, MODEL_WEIGHTS,
                                            PARAMS_FILE, REPORTS, TIMINGS, WORKSPACE_JSON, project_owned, rooted)
from pipeline.lib.project.cli import Refused, script
from pipeline.lib.project.columns import JCOMP_DEG, JOINTS_DEG, TARGET, THEORY
from pipeline.lib.project.config import for_stage, json_text, load_params, logger, read_json, split_timings
from pipeline.lib.project.writing import check_outputs, left_as_they_were, write_file, write_together
from pipeline.lib.reading.campaigns import ingested_sha256, made_by_twin
from pipeline.lib.reading.prepared import load_prepared
from pipeline.lib.robot.geometry import theory_geometry
from pipeline.lib.robot.kinematics import fk_numpy, tool_rotation
from pipeline.lib.robot.robots import load_robot
from pipeline.lib.robot.tcp import AtTcp, in_flange, probe_offsets
from pipeline.lib.runtime.compensation import delta_table, nominal_flange, orientation_targets, solve
from pipeline.lib.runtime.realtime import Realtime, check
from pipeline.lib.runtime.solvers import SOLVERS
from pipeline.lib.runtime.waypoints import as_written, compensate_program, read_waypoints, unreached
from pipeline.lib.sim.drive import drive_check, tcp_drive_check
from pipeline.lib.sim.twin import Twin

log = logger(__name__)
PARAMS = ("robot", "compensate")


def test_targets(points: pd.DataFrame) -> pd.DataFrame:
    """point_id, j1_deg..j6_deg, target_x..z: every test point of the prepared points, target = its theory
    position."""
    df = points[points.split == "test"].reset_index(drop=True)
    return df[["point_id"] + JOINTS_DEG].assign(**dict(zip(TARGET, df[THEORY].to_numpy().T)))


def read_targets(path: str, robot) -> pd.DataFrame:
    """Your own targets, read and checked as the program command's waypoints (waypoints.read_waypoints: a bad
    cell an IngestError naming file, row and column): point_id, the joints, target_x..z and, if given,
    target_rx..rz (an orientation to reach too, never dropped)."""
    df = read_waypoints(path, robot)
    missing = [c for c in TARGET if c not in df.columns]
    if missing:
        raise ValueError(f"{path}: missing column(s) {missing}; found {list(df.columns)}")
    return df


def served_model(root: Path):
    """The model the robot cell gets (model.served: the physics alone where evaluate switched the network
    off) and its workspace."""
    workspace = Workspace.from_dict(read_json(root / WORKSPACE_JSON))
    return served(load_model(root / MODEL_WEIGHTS), workspace.network), workspace


def solve_all(model, workspace, cfg: dict, robot, df: pd.DataFrame, flange_rot: np.ndarray | None = None):
    """Job 1 and 2: both solvers on df's targets (with flange_rot (n, 3, 3), their orientations too), and the
    controller path on the same positions -> (the Δθ table of compensate.solver, the comparison's summary,
    histories)."""
    q0, target = df[JOINTS_DEG].to_numpy(), df[TARGET].to_numpy()
    summary, histories = {"solver": cfg["solver"], "n_points": len(df), "orientation": flange_rot is not None}, {}
    for solver in SOLVERS:                                  # both, for the comparison; table from cfg
        s = solve(model, q0, target, cfg, robot, solver, flange_rot=flange_rot)
        res = np.linalg.norm(s.pred - target, axis=1)
        histories[solver] = s.history
        summary[solver] = {"converged_share": float(s.converged.mean()),
                           "iterations_mean": float(s.iterations.mean()),
                           "iterations_max": int(s.iterations.max()), "residual_mm_mean": float(res.mean()),
                           "residual_mm_max": float(res.max()), "seconds": s.seconds,
                           "ms_per_point": 1000 * s.seconds / len(df)}
        if s.orientation_arcsec is not None:
            summary[solver]["orientation_residual_arcsec"] = stats(s.orientation_arcsec)
        log.info("%s: %d points, %.0f%% converged, %.1f iterations on average (max %d), "
                 "residual mean %.2e mm max %.2e mm, %.3f s", solver, len(df), 100 * s.converged.mean(),
                 s.iterations.mean(), s.iterations.max(), res.mean(), res.max(), s.seconds)
        if solver == cfg["solver"]:
            table = delta_table(df["point_id"], q0, target, s, workspace)
            summary["outside_workspace"] = int((~table["in_workspace"]).sum())
    rt = Realtime(model, np.radians(robot.limits_deg), cfg["tol_mm"], workspace=workspace)   # same targets
    summary["realtime"] = check(rt, np.radians(q0), target)
    log.info("realtime (one pose per call, 2 model evaluations%s): %.0f%% verified, %.0f%% converged, "
             "residual max %.2e mm; %d of %d targets outside the trained workspace (%s table: %d)",
             ", the positions alone" if flange_rot is not None else "",
             100 * summary["realtime"]["verified_share"], 100 * summary["realtime"]["converged_share"],
             summary["realtime"]["true_residual_mm_max"], summary["realtime"]["outside_workspace"], len(df),
             cfg["solver"], summary["outside_workspace"])
    return table, summary, histories


def twin_campaign(twin_json: str, files: dict) -> str | None:
    """Which of the twin's campaigns the ingest section's files are (by their SHA-256 in ingest.json's
    `files`), or None: the drive check runs only on a campaign the twin made."""
    return made_by_twin(read_json(twin_json), ingested_sha256(files))


def twin_checks(model, cfg: dict, robot, tcp: dict | None, table: pd.DataFrame, frame: dict, made: str | None,
                flange: np.ndarray, orientation: bool = False):
    """Job 3: the twin driven to the table's recorded and compensated angles (the paper's Table 9), and
    at every `robot.tcp` where the campaign has orientation, when the campaign is the twin's main one
    (`made`) -> (compensation.json's entries, the per-point errors for drive_check.csv). flange (n, 3, 3):
    the table's poses' nominal flange orientations, targets too where `orientation`."""
    errors = pd.DataFrame(columns=["point_id"] + [f"{w}_{a}" for w in ("before", "after") for a in "xyz"])
    out = {}
    if cfg["drive_check"] and made != "main":                  # a real robot: no made-up twin result
        out["drive_check_skipped"] = f"the campaign is not the twin's ({cfg['twin']}): no drive check"
        log.info("%s", out["drive_check_skipped"])
    if made != "main":
        return out, errors
    rng = np.random.default_rng(cfg["drive_seed"])
    out["drive_check"], e = drive_check(Twin.from_json(cfg["twin"]), frame, rng, table[JOINTS_DEG].to_numpy(),
                                        table[JCOMP_DEG].to_numpy(), table[TARGET].to_numpy())
    errors = pd.DataFrame(e, columns=errors.columns[1:])
    errors.insert(0, "point_id", table["point_id"])
    if tcp and "tool_rot" in frame:
        out["tcp_drive_check"] = tcp_checks(model, cfg, robot, tcp, table, frame, flange, orientation)
    b, a = out["drive_check"]["before"], out["drive_check"]["after"]
    log.info("twin drive check on %d points: 3D error mean %.4f -> %.4f mm, max %.4f -> %.4f mm, "
             "within ±%.1f mm %.0f%% -> %.0f%%", a["n"], b["3d"]["mean"], a["3d"]["mean"],
             b["3d"]["max"], a["3d"]["max"], a["tol_mm"], 100 * b["within_tol_share"],
             100 * a["within_tol_share"])
    return out, errors


def tcp_checks(model, cfg: dict, robot, tcp: dict, table: pd.DataFrame, frame: dict, flange: np.ndarray,
               orientation: bool = False) -> dict:
    """Per `robot.tcp`: the test poses' nominal TCP positions (and where `orientation`, their nominal flange
    orientations, flange (n, 3, 3): the same for every tool) solved for through the served model (AtTcp) and
    driven on the twin (lib/sim/drive.py tcp_drive_check): Table 9 before (recorded angles) and after, and the
    flange's orientation error."""
    twin, out = Twin.from_json(cfg["twin"]), {}
    q0 = table[JOINTS_DEG].to_numpy()
    g = model.physics.geometry()
    tcp = in_flange(tcp, g)                                       # a point given in the probe's frame: carried
    for k, (name, o) in enumerate(probe_offsets(tcp, g).items()):
        at = AtTcp(model, o)
        target = fk_numpy(q0, robot, theory_geometry(robot, tcp[name]["xyz_mm"]))   # offline-programmed TCP
        s = solve(at, q0, target, cfg, robot, history=False, flange_rot=flange if orientation else None)
        rng = np.random.default_rng([cfg["drive_seed"], k + 1])
        out[name], _ = tcp_drive_check(twin, frame, rng, np.random.default_rng([cfg["drive_seed"], k + 1, 1]),
                                       q0, s.q_deg, target, o, tool_rotation(g).numpy(),
                                       flange)
        out[name]["converged_share"] = float(s.converged.mean())
        if "orientation_arcsec" in out[name]:
            o_b, o_a = out[name]["orientation_arcsec"]["before"], out[name]["orientation_arcsec"]["after"]
            log.info("twin drive check at TCP %s: the flange's orientation off its nominal target, mean %.1f -> "
                     "%.1f arcsec, max %.1f -> %.1f", name, o_b["mean"], o_a["mean"], o_b["max"], o_a["max"])
        b, a = out[name]["before"], out[name]["after"]
        log.info("twin drive check at TCP %s (%s mm in the flange) on %d points: 3D error mean %.4f -> %.4f mm, "
                 "max %.4f -> %.4f mm, within ±%.1f mm %.0f%% -> %.0f%%", name, tcp[name]["xyz_mm"], a["n"],
                 b["3d"]["mean"], a["3d"]["mean"], b["3d"]["max"], a["3d"]["max"], a["tol_mm"],
                 100 * b["within_tol_share"], 100 * a["within_tol_share"])
    return out


def convergence_table(histories: dict) -> pd.DataFrame:
    """Residual (max and mean over points, mm) per iteration and solver, for the plots."""
    return pd.DataFrame([{"solver": s, "iteration": i, "max_residual_mm": float(h[i].max()),
                          "mean_residual_mm": float(h[i].mean())}
                         for s, h in histories.items() for i in range(len(h))])


def run(params: dict, root: Path = HERE) -> dict:
    p = for_stage(params, PARAMS)
    prep = load_prepared(p["robot"], root, parts=False)
    cfg, robot, frame = {**p["compensate"], "twin": rooted(root, p["compensate"]["twin"])}, prep.robot, prep.frame
    model, workspace = served_model(root)
    targets = test_targets(prep.points)
    flange = nominal_flange(targets[JOINTS_DEG].to_numpy(), prep.nominal)   # (n, 3, 3): the same for every tool
    orientation = orientation_targets(model, cfg)
    table, summary, histories = solve_all(model, workspace, cfg, robot, targets, flange if orientation else None)
    made = twin_campaign(cfg["twin"], read_json(root / INGEST_JSON)["files"]) if cfg["drive_check"] else None
    checks, errors = twin_checks(model, cfg, robot, p["robot"]["tcp"], table, frame, made, flange, orientation)
    summary.update(checks)
    summary, timings = split_timings(summary)
    (root / TIMINGS).mkdir(parents=True, exist_ok=True)
    write_together({root / COMPENSATION_CSV: table.to_csv(index=False, float_format="%.6f"),   # the Δθ table and
                    root / COMPENSATION_PARQUET: table.to_parquet(index=False),              # what was checked of
                    root / CONVERGENCE_CSV: convergence_table(histories).to_csv(index=False),  # it: all or none
                    root / DRIVE_CSV: errors.to_csv(index=False, float_format="%.6f"),   # empty: no drive check
                    root / COMPENSATION_JSON: json_text(summary),
                    root / TIMINGS / "compensate.json": json_text(timings)})
    return summary


def main(argv=None, root: Path = HERE):
    ap = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--targets", help="CSV of your own targets (not a DVC stage run)")
    a = ap.parse_args(argv)
    params = load_params(root / PARAMS_FILE)
    if a.targets is None:
        return run(params, root)
    p = for_stage(params, PARAMS)
    model, workspace = served_model(root)
    robot = load_robot(p["robot"])
    df = read_targets(a.targets, robot)
    out = root / REPORTS / f"compensation_{Path(a.targets).stem}.csv"
    try:                                                    # before solving: compensation_convergence.csv is
        check_outputs([out], [a.targets], project_owned(root))   # the stage's
    except ValueError as e:
        raise ValueError(f"{e.args[0].split(': choose')[0]}; the table is named after the targets file: "
                         f"rename {a.targets}") from None
    try:                                                    # as the program command's waypoints: beyond the
        table = compensate_program(df, model, workspace, robot, None, p["compensate"])      # reach refused
    except Refused as e:                                    # an earlier run's table there: said
        raise Refused(f"{a.targets}: {e}; nothing written{left_as_they_were([out])}") from None
    skipped = unreached(table, robot)                       # not converged, past a limit, another configuration
    write_file(out, as_written(table, skipped).to_csv(index=False, float_format="%.6f"))
    log.info("wrote %s (%d targets, %d not reached: no angles to command, `not_reached` says why)", out,
             len(table), len(skipped))
    for pid, why in skipped.items():
        log.warning("%s not reached: %s", pid, why)


if __name__ == "__main__":
    script(__spec__.name, main)

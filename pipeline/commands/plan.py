"""Command: what to measure so that a robot program is covered: the measurement planner.

    python -m pipeline.commands.plan PROGRAM.csv --n N --out DIR [--station NAME | --tracker-mm X Y Z | --new-station]
                                                       [--seed S] [--identifiability-only]

PROGRAM.csv: the program compensator's waypoints (docs/robot-cell.md; read by the same rules,
lib/runtime/waypoints.py): point_id (optional), j1_deg..j6_deg, and optionally target_x..z (then the joints
are where to start from, and the waypoint is where the calibrated chain reaches the target; a target it reaches
only in another configuration than its joints', as the program compensator judges it, refuses the plan).
Writes, in DIR (made if missing):
    poses.csv       pose_id, j1_deg..j6_deg: the N joint configurations to measure, in the order to visit
    measure.script  URScript: def measure_campaign(): one movej per pose (rad), then a wait for the tracker
                    (plan.settle_s; with plan.handshake_io, a digital-I/O handshake too), and a movej by
                    way of a candidate pose where no order keeps a move clear; only numbers formatted here
                    and fixed text
    plan.json       the criterion, the program's coverage before and after, the predicted identifiability
                    (condition number, the standard error of every identified parameter) and the travel
The choice (lib/planner/planning.py, docs/planning.md): coverage first (every part of the correction that
leaves a waypoint outside the trained workspace, as Workspace.parts defines it), then D-optimality
(log det JᵀJ of the calibration's identified parameters, the existing campaigns' training poses
counted as measured); every pose acceptable (lib/robot/poses.py: joint limits, no singular wrist or elbow,
table and column clearance, the tracker's side with --station or --tracker-mm); ordered as a short tour
whose every movej keeps the clearance rules all along it (poses.moves_clear: the nominal chain's frame
origins; the first movej comes from wherever the arm stands): a move no order avoids goes by way of a
candidate pose both its ends may move to, and a plan with a move that has none is refused.

--station NAME      the poses are measured from tracker station NAME of reports/frame.json (the side rule
                    from its tracker position)
--tracker-mm X Y Z  from a new tracker placement at this position (base frame, mm): the side rule, and its
                    6 frame parameters identified jointly (the prediction counts them)
--new-station       from a new tracker placement whose position is not known yet (no side rule)

Needs a finished `dvc repro` (models/workspace.json, models/calibration.json, models/parts.json,
reports/calibration.json, reports/frame.json). Exit codes: 0 written; 1 refused (a target not reached, or
reached only in another configuration; no acceptable candidate: nothing written); 2 bad input (one line
naming file, row and column; no traceback).
"""
import argparse
import math
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.lib.learning.workspace import Workspace
from pipeline.lib.planner.design import Identification, MapBlock
from pipeline.lib.planner.candidates import candidates, program_joints
from pipeline.lib.planner.coverage import Coverage
from pipeline.lib.planner.planning import plan
from pipeline.lib.project.artifacts import (CALIBRATED_GEOMETRY, CALIBRATION_JSON, FRAME_JSON, PARAMS_FILE,
                                            PARTS_JSON, PARTS_REPORT, WORKSPACE_JSON, project_owned, require)
from pipeline.lib.project.cli import Refused, add_project, one_line
from pipeline.lib.project.columns import JOINTS_DEG, TARGET
from pipeline.lib.project.config import for_stage, json_text, load_params, logger, read_json
from pipeline.lib.project.writing import check_outputs, csv_text, left_as_they_were, write_together
from pipeline.lib.robot.geometry import Calibration
from pipeline.lib.robot.identify import parameter_spec
from pipeline.lib.robot.kinematics import nominal_geometry
from pipeline.lib.robot.poses import CLEARANCE, moves_clear
from pipeline.lib.robot.robots import load_robot
from pipeline.lib.runtime.paths import ROTVEC
from pipeline.lib.runtime.waypoints import read_waypoints

log = logger(__name__)
PARAMS = ("robot", "calibrate", "parts", "split", "plan")
FILES = ("poses.csv", "measure.script", "plan.json")
REACHED_MM = 0.01        # a program's target position is where the calibrated arm goes only when it gets this close


def pose_ids(n: int) -> list[str]:
    return [f"M{i + 1:0{max(3, len(str(n)))}d}" for i in range(n)]


def number(v: float, what: str) -> float:
    """A finite float for the script (a setting), or a ValueError naming it."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise ValueError(f"params.yaml plan.{what}: a positive number, got {v!r}")
    return float(v)


def measure_script(q_deg: np.ndarray, cfg: dict, via_deg: dict | None = None) -> str:
    """URScript visiting the poses q (n, 6) deg in order with movej (rad), waiting plan.settle_s at each
    for the tracker (and, with plan.handshake_io k: set standard digital output k, wait for input k,
    clear output k), by way of via_deg[k] (6,) deg, where given, from pose k to k + 1 (no measurement
    there). Only numbers formatted here and fixed text."""
    acc, vel, settle = number(cfg["acc"], "acc"), number(cfg["vel"], "vel"), number(cfg["settle_s"], "settle_s")
    io = cfg["handshake_io"]
    if io is not None and (isinstance(io, bool) or not isinstance(io, int) or not 0 <= io <= 7):
        raise ValueError(f"params.yaml plan.handshake_io: null or a standard digital I/O number 0-7, got {io!r}")
    ids, via_deg = pose_ids(len(q_deg)), via_deg or {}
    movej = lambda q: "  movej([" + ", ".join(f"{v:.12f}" for v in np.radians(q)) + "], a=acc, v=vel)"
    lines = [f"# measurement campaign planned by `python -m pipeline.commands.plan`: {len(q_deg):d} poses, "
             f"{settle:.3f} s at each for the tracker" + ("" if io is None else f", handshake on digital I/O {io:d}"),
             "def measure_campaign():", f"  acc = {acc:.6f}", f"  vel = {vel:.6f}", f"  settle = {settle:.6f}"]
    for k, (pid, q) in enumerate(zip(ids, np.asarray(q_deg, float))):
        lines += [f"  # {pid}", movej(q), "  sleep(settle)"]
        if io is not None:
            lines += [f"  set_standard_digital_out({io:d}, True)", f"  while not get_standard_digital_in({io:d}):",
                      "    sync()", "  end", f"  set_standard_digital_out({io:d}, False)"]
        if k in via_deg:
            lines += [f"  # via, not measured, to {ids[k + 1]}: the direct move breaks the clearance rules",
                      movej(np.asarray(via_deg[k], float))]
    return "\n".join(lines + ["end", ""])


TRACKER_MAX_MM = 1e5                # a tracker placement farther from the base (100 m) is a typo


def tracker_position(frame: dict, station: str | None, tracker_mm) -> tuple:
    """(tracker position (3,) mm in the base frame or None, description) from --station / --tracker-mm."""
    if station is not None:
        stations = frame.get("stations", {})
        if station not in stations:
            raise ValueError(f"--station {station!r}: not a station of {FRAME_JSON} (have {sorted(stations)})")
        R, t = np.asarray(stations[station]["R"], float), np.asarray(stations[station]["t"], float)
        return -R.T @ t, {"station": station, "new_station": False}
    if tracker_mm is not None:
        t = np.asarray(tracker_mm, float)
        if not (np.abs(t) <= TRACKER_MAX_MM).all():
            raise ValueError(f"--tracker-mm: three numbers within {TRACKER_MAX_MM:g} mm of the base, got {tracker_mm}")
        return t, {"station": None, "new_station": True}
    return None, {"station": None, "new_station": False}


def run(argv=None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m pipeline.commands.plan", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("program", help="the program's waypoints (CSV: point_id, j1_deg..j6_deg, target_x..z)")
    ap.add_argument("--n", type=int, required=True, help="how many poses to measure (at least 1)")
    ap.add_argument("--out", required=True, help="folder for poses.csv, measure.script and plan.json")
    where = ap.add_mutually_exclusive_group()
    where.add_argument("--station", help="measured from this tracker station of reports/frame.json")
    where.add_argument("--tracker-mm", type=float, nargs=3, metavar=("X", "Y", "Z"),
                       help="measured from a new tracker placement at this position (base frame, mm)")
    where.add_argument("--new-station", action="store_true",
                       help="measured from a new tracker placement, position unknown")
    ap.add_argument("--seed", type=int, default=None, help="the candidates' random stream (default plan.seed)")
    ap.add_argument("--identifiability-only", action="store_true",
                    help="choose by D-optimality alone, without the coverage phase (a comparison)")
    add_project(ap)
    a = ap.parse_args(argv)
    root = a.project
    if a.n < 1:
        raise ValueError(f"--n {a.n}: plan at least 1 pose")
    if a.seed is not None and a.seed < 0:
        raise ValueError(f"--seed {a.seed}: an integer >= 0")
    src, out = Path(a.program), Path(a.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: a file, not a folder")
    if not src.is_file():
        raise ValueError(f"{src}: no such file")
    check_outputs([out / f for f in FILES], [src], project_owned(root))   # a hard link to the program is the program
    earlier = left_as_they_were([out / f for f in FILES])
    p = for_stage(load_params(root / PARAMS_FILE), PARAMS)
    cfg = p["plan"]
    robot = load_robot(p["robot"])
    robot.check_joint_speed(cfg["vel"], "plan.vel")
    require(root, (WORKSPACE_JSON, CALIBRATED_GEOMETRY, PARTS_JSON, CALIBRATION_JSON, FRAME_JSON))
    measure_script(np.zeros((0, 6)), cfg)                           # the script's settings, checked before work
    df = read_waypoints(src, robot)
    cal_json, report, frame = (read_json(root / f) for f in (CALIBRATED_GEOMETRY, CALIBRATION_JSON, FRAME_JSON))
    cal = Calibration.from_dict(cal_json)
    q_wp = df[JOINTS_DEG].to_numpy()
    unused = [c for c in ROTVEC if c in df]                          # said below and in plan.json, not dropped unseen
    if TARGET[0] in df:                                             # positions: where the calibrated arm goes
        q_wp, miss, flipped = program_joints(q_wp, df[TARGET].to_numpy(), cal.geometry, robot.limits_deg)
        far = miss > REACHED_MM
        if far.any():
            raise Refused(f"{src}: {int(far.sum())} target(s) the calibrated arm does not reach from their joints "
                          "within its limits; nothing written: " + "; ".join(
                              f"{p}: {m:.1f} mm short" for p, m in zip(df.point_id[far][:10], miss[far][:10]))
                          + earlier)
        flips = [f"{p}: {why}" for p, why in zip(df.point_id, flipped) if why]
        if flips:                                   # the program compensator refuses them: no poses around them
            raise Refused(f"{src}: {len(flips)} target(s) the calibrated arm reaches only in another configuration "
                          "than their joints' (the program compensator refuses them too); nothing written: "
                          + "; ".join(flips[:10]) + earlier)
    tracker, station = tracker_position(frame, a.station, a.tracker_mm)
    station["new_station"] |= a.new_station
    a_cfg = p["parts"]["angle_map"]
    cov = Coverage.from_workspace(Workspace.from_dict(read_json(root / WORKSPACE_JSON)), a_cfg["reach_deg"],
                                  a_cfg["fade_deg"])
    robot_names = {s[0] for s in parameter_spec(p["calibrate"])}      # not the further stations' frames
    ident = Identification(cal.geometry, p["calibrate"], [n for n in cal_json["identified"] if n in robot_names],
                           report["residual_sigma_mm"], station["new_station"],       # orientation rows where
                           weight=report.get("orientation_weight_mm_per_rad"))         # calibrate had them
    seed = cfg["seed"] if a.seed is None else a.seed
    nominal = nominal_geometry(robot)
    cand = candidates(q_wp, np.random.default_rng(seed), nominal, cfg["rules"], robot.limits_deg,
                      cov, cfg["per_waypoint"], cfg["region"], cfg["region_margin_deg"], tracker,
                      link_q=cov.train_q if station["new_station"] else None)
    maps = MapBlock(cov.joints, a_cfg["knot_deg"], a_cfg["prior_arcsec"], a_cfg["smooth_arcsec"],
                    p["parts"]["noise_mm"]) if cov.joints else None
    if len(cand["q"]) == 0:
        raise Refused(f"{src}: no acceptable candidate pose near the program (rules failed: "
                      f"{ {k: v for k, v in cand['rejected_by'].items() if v} }); nothing written. "
                      "Check params.yaml plan.rules and the tracker's position" + earlier)
    if a.n > len(cand["q"]):                         # said now, not after planning every candidate (minutes)
        raise ValueError(f"--n {a.n}: only {len(cand['q'])} candidate poses near the program pass the rules "
                         "(plan.per_waypoint, plan.region, plan.rules): ask for at most that many; nothing written"
                         + earlier)
    result = plan(q_wp, a.n, cov, ident, cand, cfg["cover_k"], not a.identifiability_only,
                  train_fraction=p["split"]["fractions"][0], maps=maps,
                  move_ok=lambda q0, q1: bool(moves_clear(q0, q1, nominal, cfg["rules"])[0]))
    ids = pose_ids(len(result.q_deg))
    rep = result.report
    clearance = rep["travel"]["clearance"]
    if clearance["failing"]:
        i, j = clearance["failing"][0]
        raise Refused(f"{src}: the move {ids[i]} -> {ids[j]} between planned poses breaks "
                      f"{' or '.join(k for k in CLEARANCE if cfg['rules'].get(k) is not None)} (plan.rules) on the "
                      "way, and no candidate pose lets it go by; nothing written (plan another --seed or fewer "
                      "poses, --n)" + earlier)
    for v in clearance["via"]:
        v["after"] = ids[v["after"]]
    rep["identifiability"]["reported_se"] = {k: report["estimates"][k]["se"] for k in ident.names
                                             if k in report.get("estimates", {})}
    if (root / PARTS_REPORT).exists() and read_json(root / PARTS_JSON)["enabled"]:   # what calibration + maps leave
        s = read_json(root / PARTS_REPORT)["splits"]["train"]["calibrated_parts"]["rms_mm"] / np.sqrt(3.0)
        rep["identifiability"]["sigma_after_maps_mm"] = float(s)
        rep["identifiability"]["se_scale_after_maps"] = float(s / ident.sigma_mm)
    wp_ids = df["point_id"].tolist()
    for w, entry in enumerate(rep["coverage"]["per_waypoint"]):
        entry["point_id"] = wp_ids[w]
    rep = {"program": str(src), "n_waypoints": len(df), "seed": seed, "columns_not_used": unused,
           "tracker": {**station, "position_mm": None if tracker is None else np.round(tracker, 3).tolist(),
                       "side_rule_deg": None if tracker is None else cfg["rules"]["tracker_side_deg"]},
           **rep,
           "poses": [{"pose_id": i, "role": r, "near": None if w < 0 else wp_ids[w]}
                     for i, r, w in zip(ids, result.role, result.near)],
           "settings": cfg, "files": {f: str(out / f) for f in FILES}}
    out.mkdir(parents=True, exist_ok=True)
    poses = pd.DataFrame(result.q_deg, columns=JOINTS_DEG)
    poses.insert(0, "pose_id", ids)
    write_together({out / "poses.csv": csv_text(poses),
                    out / "measure.script": measure_script(result.q_deg, cfg, result.via_deg),
                    out / "plan.json": json_text(rep)},
                   [src])
    c, i, t = rep["coverage"], rep["identifiability"], rep["travel"]
    cond = lambda x: "-" if x is None else f"{x:.1f}"
    print(f"{len(ids)} poses to measure ({rep['n_coverage']} for coverage, {rep['n_d_optimal']} D-optimal) for "
          f"{len(df)} waypoints: covered {100 * c['before']['all']:.0f}% -> {100 * c['after']['all']:.0f}% "
          f"({100 * c['after_expected_split']:.0f}% expected after the 8:1:1 split); condition number "
          f"{cond(i['before']['condition_number'])} -> {cond(i['after']['condition_number'])}; travel "
          f"{t['max_joint_deg']:.0f} deg of largest joint moves")
    if len(ids) < a.n:
        print(f"  only {len(ids)} of the {a.n} poses asked for: no other candidate pose passed the rules "
              "(plan.per_waypoint, plan.region)")
    if unused:
        print(f"  {', '.join(unused)} not used: the poses are planned around each waypoint's joints and position; "
              "the orientation those joints give is the one measured")
    if c["parts_short_after"]:
        print(f"  {c['parts_short_after']} uncovered part(s) got fewer than {cfg['cover_k']} poses: "
              "plan more poses (--n) to cover them")
    log.info("wrote %s", ", ".join(str(out / f) for f in FILES))
    return rep


def main(argv=None):
    return one_line("pipeline.commands.plan", run, argv)


if __name__ == "__main__":
    main()

"""`bench plan`: the measurement planner's loop closed on the twin (issue 23); writes (and merges into)
reports/bench/plan.json, saved as each run finishes.

    python -m pipeline.commands.bench plan [--n 60] [--seeds 139 140 141]                the closed loop
    python -m pipeline.commands.bench plan --curve [--sizes 25 50 100 200 400 700] [--seeds 139 140 141]
                                                                                the learning curve
    python -m pipeline.commands.bench plan --curve --sizes 700 --extend                 one more size on it

The closed loop, per seed (the training seed; the planner's candidates, the random poses and every
measurement's noise are drawn from it too):
  program     `--waypoints` poses at the side of the arm (joint 1 at 70-150°: twin.REGIONS["side"]),
              where the default campaign never goes; the same program for every seed;
  none        the pipeline on the default campaign (data/raw): today's project; the program compensated
              and driven there, and the compensate stage's drive check on its test points (the driven
              error inside the default campaign's workspace);
  planned     `python -m pipeline.commands.plan program.csv --n N --tracker-mm ...` run in that project, its poses
              measured by the twin from a tracker station of their own placed to see the side
              (STATION), as campaigns.more `plan`; the pipeline re-run from ingest (a scratch folder per
              variant, as bench real does); the program compensated (lib/runtime/waypoints.py compensate_program)
              and driven on the twin (Twin.drive);
  random      the same, N poses drawn at random in the program's region (twin.sample_poses, side);
  identifiability   the same, N poses chosen by D-optimality alone (`plan --identifiability-only`).
Reported per variant: the program's driven error (mean 3D, mm; beside it the program's noise floor, where
a perfect model would drive it: the arm's repeatability and the tracker's noise, twin.noise_floor), its
share inside the trained workspace, the test and the independent campaign's (twin_side) error, the
identified parameters; the goals'
ratios (planned / the drive check inside the default workspace; planned against random); and the
predicted standard errors against (a) the spread of the identified parameters over the seeds and (b)
a Monte Carlo: the default campaign's training poses and the planned ones measured again
`--se-check` times with fresh noise, identified each time (`identify`, new station jointly).

The learning curve (--curve), per size N, seed and variant, from scratch (no other campaign):
  random      N poses at random in the front (the default campaign's rules and region);
  planned     N poses chosen by the planner (lib/planner/planning.py plan) for a front work region (`--work`
              waypoints at random in the front, fixed), with no training poses yet: coverage at the
              default campaign's radius, then D-optimality;
measured by the twin from the default tracker pose, trained on alone; judged on its test split, on a
fixed front campaign of 200 poses measured from the same tracker (validate `front_check`, frame
same: comparable across variants) and on twin_side (refit). Reported: the fewest poses reaching a
front_check (and test) error of 0.1 mm per variant, with the paper's 724 samples beside them.
"""
import copy
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from scipy.spatial.transform import Rotation

from pipeline import stages
from pipeline.commands.bench.common import BENCH, ROOT, machine
from pipeline.commands.bench.real import absolute_paths, overridden
from pipeline.lib.learning.checkpoint import load_model
from pipeline.lib.learning.metrics import seed_std
from pipeline.lib.learning.workspace import Workspace, workspace_radius
from pipeline.lib.planner.design import Identification
from pipeline.lib.planner.candidates import candidates
from pipeline.lib.planner.coverage import Coverage
from pipeline.lib.planner.planning import plan
from pipeline.lib.project.artifacts import (CALIBRATED_GEOMETRY, CALIBRATION_JSON, COMPENSATION_JSON,
                                            FRAME_JSON, METRICS_JSON, MODEL_WEIGHTS, PARAMS_FILE, VALIDATION_DIR,
                                            WORKSPACE_JSON)
from pipeline.lib.project.columns import JCOMP_DEG, JOINTS_DEG
from pipeline.lib.project.config import load_params, logger, read_json, write_json, yaml_text
from pipeline.lib.reading.campaigns import write_pair
from pipeline.lib.robot.frames import to_base
from pipeline.lib.robot.geometry import Calibration, theory_geometry
from pipeline.lib.robot.identify import geometry_jacobian, identifiability, identify
from pipeline.lib.robot.kinematics import DTYPE, fk, nominal_geometry
from pipeline.lib.robot.robots import load_robot
from pipeline.lib.runtime.waypoints import compensate_program
from pipeline.lib.sim.twin import REGIONS, Twin, sample_poses

log = logger(__name__)
OUT = BENCH / "plan.json"
PROGRAM_SEED = 2323                                 # the side program (fixed: the engineer's program)
WORK_SEED = 2324                                    # the learning curve's front work region
FRONT_CHECK = {"seed": 7231, "n": 200}              # the learning curve's fixed front test campaign
# The planned campaign's tracker station: 3 m from the base, towards the middle of the side region, 0.8 m
# up, turned any way (the orientation from the twin's second-station seed's stream).
STATION = {"distance_mm": 3000.0, "height_mm": 800.0, "rotation_seed": 726}
VARIANTS = ("planned", "random", "identifiability")
STAGES = ("ingest", "frame", "theory", "split", "calibrate", "parts", "train", "baselines", "evaluate")
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}


def station_pose(region: str = "side") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, t, tracker position in the base frame mm) of the planned campaign's tracker: P = R Q + t."""
    az = np.radians(np.mean(REGIONS[region][1]))                  # azimuth from -x (poses.azimuth)
    pos = np.array([-np.cos(az), np.sin(az), 0.0]) * STATION["distance_mm"] + [0.0, 0.0, STATION["height_mm"]]
    R = Rotation.random(random_state=np.random.default_rng(STATION["rotation_seed"])).as_matrix()
    return R, -R @ pos, pos


def write_campaign(folder: Path, q_deg: np.ndarray, twin: Twin, rng: np.random.Generator, prefix: str) -> dict:
    """The twin measures poses q (deg) once each: joints.csv and tracker.csv in `folder` (the data
    format); returns the ingest overrides naming them."""
    ids = [f"{prefix}{i + 1:04d}" for i in range(len(q_deg))]
    joints = pd.DataFrame(np.round(q_deg, 6), columns=JOINTS_DEG)
    joints.insert(0, "point_id", ids)
    tracker = pd.DataFrame(twin.drive(joints[JOINTS_DEG].to_numpy(), rng), columns=["X", "Y", "Z"])
    tracker.insert(0, "Name", ids)
    return write_pair(folder, joints, tracker)


def run_pipeline(folder: Path, params: dict, compensate: bool = True) -> dict:
    """The pipeline's stages in `folder` (made), on params written to its params.yaml, in this process;
    returns what the benchmark reads back."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / PARAMS_FILE).write_text(yaml_text(params))
    for name in params["campaigns"]["more"] or {}:
        stages.run("ingest", ["campaign", name], folder)
    for name in STAGES:
        stages.run(name, (), folder)
    if compensate:
        stages.run("compensate", (), folder)
    for name in params["validate"]["campaigns"] or {}:
        stages.run("validate", ["campaign", name], folder)
    metrics, cal = read_json(folder / METRICS_JSON), read_json(folder / CALIBRATION_JSON)
    out = {"test_3d_mae": {k: v["test"]["3d"]["mae"] for k, v in metrics["baselines"].items()},
           "test_3d_mae_per_campaign": {c: {k: v[k]["test"]["mae"] for k in v if k not in ("station", "n")}
                                        for c, v in metrics["campaigns"].items()},
           "validation": {n: {"mean_3d_mm": (v := read_json(folder / VALIDATION_DIR / f"{n}.json"))["mean_3d_mm"],
                              "in_workspace_share": v["in_workspace_share"]}
                          for n in params["validate"]["campaigns"] or {}},
           "calibration": {k: {"delta": e["delta"], "se": e["se"], "unit": e["unit"]}
                           for k, e in cal["estimates"].items()},
           "residual_sigma_mm": cal["residual_sigma_mm"]}
    if compensate and "drive_check" in (c := read_json(folder / COMPENSATION_JSON)):
        out["drive_check_test_points_mm"] = c["drive_check"]["after"]["3d"]["mean"]
    return out


def drive_program(folder: Path, params: dict, program: pd.DataFrame, twin: Twin, rng) -> dict:
    """The program compensated by the project in `folder` (the program compensator's library) and driven
    on the twin: its 3D error before and after (mm), in the trained workspace, uncertainty; and, at the
    compensated joints against the twin's noise-free truth (base frame by the fitted frame), the error
    of the model, of its physics branch (calibration + error maps) and of the calibration alone."""
    robot = load_robot(params["robot"])
    frame = read_json(folder / FRAME_JSON)
    ws = Workspace.from_dict(read_json(folder / WORKSPACE_JSON))
    model = load_model(folder / MODEL_WEIGHTS)
    table = compensate_program(program, model, ws, robot, theory_geometry(robot, frame["tool_mm"]),
                               params["compensate"])
    calibration = Calibration.from_dict(read_json(folder / CALIBRATED_GEOMETRY)).geometry
    q0, q1 = program[JOINTS_DEG].to_numpy(), table[JCOMP_DEG].to_numpy()
    target = table[["target_x", "target_y", "target_z"]].to_numpy()
    before = np.linalg.norm(to_base(twin.drive(q0, rng), frame) - target, axis=1)
    after = np.linalg.norm(to_base(twin.drive(q1, rng), frame) - target, axis=1)
    truth = to_base(twin.to_tracker(twin.expected_position(q1)), frame)
    qt = torch.as_tensor(np.radians(q1), dtype=DTYPE)
    with torch.no_grad():
        pred = {"model": model(qt)[0].numpy(), "physics": model.physics(qt).numpy(),
                "calibration": fk(qt, calibration).numpy()}
    return {"driven_before_mm": float(before.mean()), "driven_mm": float(after.mean()),
            "driven_max_mm": float(after.max()), "converged_share": float(table.converged.mean()),
            "in_workspace_share": float(table.in_workspace.mean()),
            "in_angle_maps_share": float(ws.parts(q1)["angle_map"].mean()),
            "uncertainty_mm_mean": float(table.uncertainty_mm.mean()),
            "noise_free_error_mm": {k: float(np.linalg.norm(v - truth, axis=1).mean()) for k, v in pred.items()}}


def base_params(overrides: list[str], epochs: int | None, seed: int) -> dict:
    p = absolute_paths(overridden(load_params(ROOT / "params.yaml"), overrides))
    if epochs:
        p["train"]["max_epochs"] = epochs
    p["model"]["init_seed"], p["train"]["seed"] = seed, seed
    p["baselines"]["dnn"], p["baselines"]["other_physics"] = False, False
    p["compensate"]["twin"] = str(ROOT / load_params(ROOT / "params.yaml")["compensate"]["twin"])
    p["compensate"]["drive_check"] = True
    return p


def plan_command(project: Path, program_csv: Path, n: int, out: Path, tracker_mm, seed: int, only_d: bool) -> dict:
    """`python -m pipeline.commands.plan` in the project, as another tool drives it (tracker_mm None: measured from
    the project's first station); its plan.json."""
    cmd = [sys.executable, "-m", "pipeline.commands.plan", str(program_csv), "--n", str(n), "--out", str(out),
           "--seed", str(seed)] + ([] if tracker_mm is None else ["--tracker-mm", *[f"{v:.3f}" for v in tracker_mm]])
    subprocess.run(cmd + (["--identifiability-only"] if only_d else []), cwd=project, env=ENV, check=True)
    return read_json(out / "plan.json")


def se_check(train_q: np.ndarray, plan_q: np.ndarray, twin: Twin, station: Twin, cfg: dict, seeds: int,
             predicted: dict) -> dict:
    """The planned poses' predicted standard errors against a Monte Carlo, `seeds` identifications
    (`identify`, the planned station's frame jointly) of the training poses (measured from the default
    station) and the planned ones (from their own), mapped to the base frame with each tracker's true
    pose, in two ways:
      noise     the same poses measured again with the twin's noise: the spread the noise alone makes
                (the twin's unmodelled errors, the same at every run, do not spread);
      campaign  a fresh default campaign each run (as many poses, at random in the front, the twin's
                rules) beside the same planned poses: the unmodelled errors, met at other poses, spread
                too, as from one real campaign to the next.
    Per robot parameter: the spread (std) over the runs, and its ratio to the prediction."""
    g0 = nominal_geometry(twin.robot)
    out = {"runs": seeds}
    for mode in ("noise", "campaign"):
        runs = []
        for s in range(seeds):
            rng = np.random.default_rng([9000, s])
            tq = train_q if mode == "noise" else sample_poses(len(train_q), rng, twin.robot, region="front")
            q = np.vstack([tq, plan_q])
            p = np.vstack([to_base(twin.drive(tq, rng), {"R": twin.R, "t": twin.t}),
                           to_base(station.drive(plan_q, rng), {"R": station.R, "t": station.t})])
            idx = np.r_[np.zeros(len(tq), int), np.full(len(plan_q), int(station is not twin))]
            _, rep = identify(np.radians(q), p, g0, cfg, idx, ["main", "plan"] if station is not twin else None)
            runs.append({k: v["delta"] for k, v in rep["estimates"].items()})
        names = [k for k in predicted if all(k in r for r in runs) and predicted[k]["se"]]
        spread = {k: float(np.std([r[k] for r in runs], ddof=1)) for k in names}
        ratio = {k: spread[k] / predicted[k]["se"] for k in names}
        out[mode] = {"spread": spread, "ratio": ratio, "ratio_median": float(np.median(list(ratio.values()))),
                     "within_factor_2_share": float(np.mean([0.5 <= r <= 2.0 for r in ratio.values()]))}
    out["predicted_se"] = {k: predicted[k]["se"] for k in out["noise"]["spread"]}
    return out


def side_program(twin: Twin, n_wp: int) -> pd.DataFrame:
    """The engineer's program at the side of the arm (module docstring): point_id, j1_deg..j6_deg."""
    program = pd.DataFrame(sample_poses(n_wp, np.random.default_rng(PROGRAM_SEED), twin.robot, region="side"),
                           columns=JOINTS_DEG)
    program.insert(0, "point_id", [f"W{i + 1:03d}" for i in range(n_wp)])
    return program


def closed_loop_seed(seed: int, n: int, n_wp: int, variants, overrides, epochs, se_runs: int, scratch: Path,
                     new_station: bool = True) -> dict:
    """One seed of the closed loop (module docstring): every variant's record. new_station False: the new
    poses measured from the default campaign's tracker (its station, its frame)."""
    twin = Twin.from_json(ROOT / load_params(ROOT / "params.yaml")["compensate"]["twin"])
    R, t, tracker = station_pose("side")
    station = Twin(twin.seed, twin.errors, (R, t)) if new_station else twin
    tracker = tracker if new_station else None
    program = side_program(twin, n_wp)
    program_csv = scratch / "program.csv"
    program.to_csv(program_csv, index=False, float_format="%.6f")
    params = base_params(overrides, epochs, seed)
    out = {"program_noise_floor_mm": twin.noise_floor(program[JOINTS_DEG].to_numpy())}
    t0 = time.perf_counter()
    none = scratch / f"none-{seed}"
    out["none"] = run_pipeline(none, params)
    out["none"]["program"] = drive_program(none, params, program, twin, np.random.default_rng([seed, 18]))
    log.info("seed %d, no new campaign: program driven %.4f mm (%.0f%% in the workspace); test points %.4f mm",
             seed, out["none"]["program"]["driven_mm"], 100 * out["none"]["program"]["in_workspace_share"],
             out["none"].get("drive_check_test_points_mm", np.nan))
    for v in variants:
        plan_json = None
        if v == "random":
            q = sample_poses(n, np.random.default_rng([seed, 1]), twin.robot, region="side")
        else:
            plan_json = plan_command(none, program_csv, n, scratch / f"{v}-{seed}-plan", tracker, seed,
                                     v == "identifiability")
            q = pd.read_csv(scratch / f"{v}-{seed}-plan" / "poses.csv")[JOINTS_DEG].to_numpy()
        folder = scratch / f"{v}-{seed}"
        ingest = write_campaign(folder / "campaign", q, station, np.random.default_rng([seed, 2]), "N")
        p = copy.deepcopy(params)
        p["campaigns"]["more"] = {"plan": {"ingest": ingest,
                                           "station": "plan" if new_station else params["campaigns"]["station"]}}
        rec = run_pipeline(folder, p)
        rec["program"] = drive_program(folder, p, program, twin, np.random.default_rng([seed, 18]))
        rec["n_poses"] = int(len(q))
        if plan_json is not None:
            rec["plan"] = {"coverage": {k: plan_json["coverage"][k] for k in ("before", "after", "after_expected_split")},
                           "n_coverage": plan_json["n_coverage"], "n_d_optimal": plan_json["n_d_optimal"],
                           "condition_number": {w: plan_json["identifiability"][w]["condition_number"]
                                                for w in ("before", "after")},
                           "predicted_se": {k: v_["se"] for k, v_ in plan_json["identifiability"]["after"]["se"].items()},
                           "se_scale_after_maps": plan_json["identifiability"].get("se_scale_after_maps"),
                           "angle_maps": plan_json["identifiability"]["angle_maps"],
                           "travel": {k: plan_json["travel"][k] for k in ("max_joint_deg", "joint_space_deg")}}
            if v == "planned" and se_runs > 1:
                cfg = load_params(none / "params.yaml")["calibrate"]
                train_q = np.asarray(read_json(none / WORKSPACE_JSON)["train_q_deg"])
                rec["se_check"] = se_check(train_q, q, twin, station, cfg, se_runs,
                                           plan_json["identifiability"]["after"]["se"])
        out[v] = rec
        log.info("seed %d, %s (%d poses): program driven %.4f mm (%.0f%% in the workspace), test %.4f mm", seed, v,
                 len(q), rec["program"]["driven_mm"], 100 * rec["program"]["in_workspace_share"],
                 rec["test_3d_mae"].get("spi_boter_calibrated", np.nan))
    out["seconds"] = time.perf_counter() - t0
    return out


def stats(values) -> dict:
    v = [x for x in values if x is not None]
    return {"mean": float(np.mean(v)), "std": seed_std(v), "runs": v} if v else {"mean": None}


def closed_loop_summary(runs: dict, variants) -> dict:
    """Means over the seeds and the goals' ratios."""
    seeds = sorted(runs)
    model = lambda r: next((v for k, v in r["test_3d_mae"].items() if k.startswith("spi_boter")), None)
    out = {"seeds": seeds, "variants": {}}
    for v in ("none",) + tuple(variants):
        rs = [runs[s][v] for s in seeds if v in runs[s]]
        if not rs:
            continue
        out["variants"][v] = {
            "program_driven_mm": stats([r["program"]["driven_mm"] for r in rs]),
            "program_in_workspace_share": stats([r["program"]["in_workspace_share"] for r in rs]),
            "program_in_angle_maps_share": stats([r["program"]["in_angle_maps_share"] for r in rs]),
            "test_3d_mae_model": stats([model(r) for r in rs]),
            "twin_side_model_mm": stats([r["validation"].get("twin_side", {}).get("mean_3d_mm", {}).get("model")
                                        for r in rs]),
            "drive_check_test_points_mm": stats([r.get("drive_check_test_points_mm") for r in rs])}
    V = out["variants"]
    ref = V["none"]["drive_check_test_points_mm"]["mean"]
    if "planned" in V and ref:
        out["goal_planned_vs_inside_default_workspace"] = {
            "planned_mm": V["planned"]["program_driven_mm"]["mean"], "inside_default_workspace_mm": ref,
            "ratio": V["planned"]["program_driven_mm"]["mean"] / ref, "goal": "<= 1.2"}
    if "planned" in V and "random" in V:
        p, r = V["planned"]["program_driven_mm"]["mean"], V["random"]["program_driven_mm"]["mean"]
        out["goal_planned_vs_random"] = {"planned_mm": p, "random_mm": r, "below_random": 1 - p / r, "goal": ">= 0.20"}
        floor = [runs[s]["program_noise_floor_mm"] for s in seeds if "program_noise_floor_mm" in runs[s]]
        if floor:     # a perfect model still reads the arm's repeatability and the tracker's noise
            out["goal_planned_vs_random"].update(
                program_noise_floor_mm=float(np.mean(floor)), perfect_model_below_random=1 - float(np.mean(floor)) / r)
    if "planned" in V:                               # predicted se against the spread over the seeds
        recs = [runs[s]["planned"] for s in seeds if "planned" in runs[s]]
        pred = {k: np.mean([r["plan"]["predicted_se"][k] for r in recs]) for k in recs[0]["plan"]["predicted_se"]
                if all(r["plan"]["predicted_se"].get(k) for r in recs)}
        common = [k for k in pred if all(k in r["calibration"] for r in recs)]
        if len(recs) > 1 and common:
            spread = {k: float(np.std([r["calibration"][k]["delta"] for r in recs], ddof=1)) for k in common}
            ratio = {k: spread[k] / pred[k] for k in common}
            out["se_vs_spread_over_seeds"] = {
                "note": "the default campaign's measurements are the same in every seed: only the planned "
                        "campaign's noise and poses vary, so this spread is a lower bound",
                "ratio": ratio, "ratio_median": float(np.median(list(ratio.values()))),
                "within_factor_2_share": float(np.mean([0.5 <= x <= 2 for x in ratio.values()]))}
        checks = [r["se_check"] for r in recs if "se_check" in r]
        scale = recs[0]["plan"].get("se_scale_after_maps")
        if checks:
            out["se_vs_monte_carlo"] = {"runs": checks[0]["runs"], "se_scale_after_maps": scale,
                                        **({f"{m}_ratio_median_to_after_maps_se": checks[0][m]["ratio_median"] / scale
                                            for m in ("noise", "campaign")} if scale else {}),
                                        **{m: {k: checks[0][m][k] for k in ("ratio_median", "within_factor_2_share")}
                                           for m in ("noise", "campaign")}}
    return out


# ----------------------------------------------------------------------------- the learning curve

def scratch_plan(n: int, seed: int, robot, params: dict, reference_q: np.ndarray, n_work: int) -> tuple:
    """n poses planned from scratch for the front work region (module docstring); (poses, plan report)."""
    q_wp = sample_poses(n_work, np.random.default_rng(WORK_SEED), robot, region="front")
    a = params["parts"]["angle_map"]
    cov = Coverage(np.zeros((0, 6)), workspace_radius(reference_q, params["workspace"]["radius_quantile"]),
                   list(a["joints"]), a["reach_deg"], a["fade_deg"])
    g = nominal_geometry(robot)
    cfg = params["plan"]
    cand = candidates(q_wp, np.random.default_rng([seed, n, 3]), g, cfg["rules"], robot.limits_deg, cov,
                      cfg["per_waypoint"], cfg["region"], cfg["region_margin_deg"])
    J, spec = geometry_jacobian(torch.as_tensor(np.radians(cand["q"]), dtype=DTYPE), g, params["calibrate"])
    keep = identifiability(J, [s[0] for s in spec], params["calibrate"]["rank_tol"])["keep"]
    ident = Identification(g, params["calibrate"], [s[0] for s, k in zip(spec, keep) if k], 0.05)
    pl = plan(q_wp, n, cov, ident, cand, cfg["cover_k"], True, train_fraction=params["split"]["fractions"][0])
    return pl.q_deg, pl.report


def curve_run(n: int, seed: int, variant: str, overrides, epochs, scratch: Path, front_check: dict,
              n_work: int) -> dict:
    twin = Twin.from_json(ROOT / load_params(ROOT / "params.yaml")["compensate"]["twin"])
    params = base_params(overrides, epochs, seed)
    params["compensate"]["drive_check"] = False
    reference_q = pd.read_csv(ROOT / "data/raw/joints.csv")[JOINTS_DEG].to_numpy()
    rec = {}
    if variant == "random":
        q = sample_poses(n, np.random.default_rng([seed, n, 2]), twin.robot, region="front")
    else:
        q, report = scratch_plan(n, seed, twin.robot, params, reference_q, n_work)
        rec["plan"] = {"coverage_after": report["coverage"]["after"], "n_coverage": report["n_coverage"],
                       "condition_number": report["identifiability"]["after"]["condition_number"]}
    folder = scratch / f"curve-{variant}-{n}-{seed}"
    params["ingest"].update(write_campaign(folder / "campaign", q, twin, np.random.default_rng([seed, n, 4]), "C"))
    params["campaigns"]["more"] = {}
    params["validate"]["campaigns"]["front_check"] = {"ingest": front_check, "frame": "same", "commanded": None}
    rec.update(run_pipeline(folder, params, compensate=False))
    rec["n_poses"] = int(len(q))
    return rec


def curve_summary(runs: dict) -> dict:
    """Per variant and size: the means over seeds; the fewest poses reaching 0.1 mm."""
    out = {}
    for variant, by_n in runs.items():
        rows = {}
        for n, by_seed in sorted(by_n.items(), key=lambda kv: int(kv[0])):
            rs = list(by_seed.values())
            model = [next((v for k, v in r["test_3d_mae"].items() if k.startswith("spi_boter")), None) for r in rs]
            rows[n] = {"test_3d_mae_model": stats(model),
                       "test_3d_mae_calibrated": stats([r["test_3d_mae"].get("calibrated_dh") for r in rs]),
                       "front_check_model_mm": stats([r["validation"]["front_check"]["mean_3d_mm"]["model"] for r in rs]),
                       "twin_side_model_mm": stats([r["validation"]["twin_side"]["mean_3d_mm"]["model"] for r in rs]),
                       "seeds": len(rs)}
        fewest = lambda key: next((int(n) for n, r in rows.items() if r[key]["mean"] is not None
                                   and r[key]["mean"] <= 0.1), None)
        out[variant] = {"by_size": rows, "fewest_poses_front_check_le_0.1mm": fewest("front_check_model_mm"),
                        "fewest_poses_test_le_0.1mm": fewest("test_3d_mae_model")}
    out["paper_samples"] = 724
    return out


def extended_curve(key: str, rec: dict, sizes) -> tuple[dict, list]:
    """The curve plan.json holds under key, to be extended by `sizes` (those it lacks); refused unless it
    was run with rec's seeds, overrides, epochs and work region."""
    old = read_json(OUT).get(key) if OUT.exists() else None
    if old is None:
        raise SystemExit(f"plan --extend: {OUT} holds no '{key}' to extend")
    for k in ("overrides", "epochs", "seeds", "work_waypoints"):
        if old.get(k) != rec[k]:
            raise SystemExit(f"plan --extend: '{key}' was run with {k} {old.get(k)!r}, not {rec[k]!r}")
    new = [n for n in sizes if n not in old["sizes"]]
    old["sizes"] = sorted(old["sizes"] + new)
    old.setdefault("extensions", []).append({"sizes": new, "machine": rec["machine"]})
    return old, new


# ----------------------------------------------------------------------------- the command

def save(key: str, rec: dict) -> None:
    """Merge one record into plan.json, re-read first (a closed loop and a curve may run side by side)."""
    out = read_json(OUT) if OUT.exists() else {}
    out[key] = rec
    write_json(OUT, out)


def bench_plan(n: int = 60, seeds=(139, 140, 141), waypoints: int = 20, variants=VARIANTS, curve: bool = False,
               sizes=(25, 50, 100, 200, 400, 700), overrides=(), epochs: int | None = None, se_runs: int = 5,
               threads: int | None = None, work: int = 40, keep: str | None = None, new_station: bool = True,
               extend: bool = False) -> dict:
    """The closed loop (or, with curve, the learning curve); merged into reports/bench/plan.json. keep: a
    folder for the scratch projects, kept (default: a temporary one, removed). extend (curve): add `sizes`
    to the curve plan.json holds for the same seeds, overrides, epochs and work region, keeping its runs."""
    if threads:
        torch.set_num_threads(threads)
    key = ("learning_curve" if curve else "closed_loop" + ("" if new_station else "_same_station")) \
        + ("@" + ",".join(overrides) if overrides else "")
    rec = {"machine": machine(), "overrides": list(overrides), "epochs": epochs, "seeds": list(seeds)}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        scratch = Path(keep or tmp)
        scratch.mkdir(parents=True, exist_ok=True)
        if not curve:
            rec.update(n=n, waypoints=waypoints, variants=list(variants), new_station=new_station, station=dict(zip(
                ("R", "t", "position_mm"), (x.tolist() for x in station_pose("side")))) if new_station else "the default's",
                runs={})
            for s in seeds:
                rec["runs"][str(s)] = closed_loop_seed(s, n, waypoints, variants, overrides, epochs,
                                                       se_runs if s == seeds[0] else 0, scratch, new_station)
                rec["summary"] = closed_loop_summary(rec["runs"], variants)
                rec["seconds"] = time.perf_counter() - t0
                save(key, rec)
        else:
            twin = Twin.from_json(ROOT / load_params(ROOT / "params.yaml")["compensate"]["twin"])
            q_fc = sample_poses(FRONT_CHECK["n"], np.random.default_rng(FRONT_CHECK["seed"]), twin.robot)
            front_check = write_campaign(scratch / "front_check", q_fc, twin,
                                         np.random.default_rng(FRONT_CHECK["seed"] + 1), "F")
            rec.update(sizes=list(sizes), work_waypoints=work, runs={"planned": {}, "random": {}})
            if extend:
                rec, sizes = extended_curve(key, rec, sizes)
            seconds0 = rec.get("seconds", 0.0)
            for size in sizes:
                for s in seeds:
                    for v in ("random", "planned"):
                        r = curve_run(size, s, v, overrides, epochs, scratch, front_check, work)
                        rec["runs"][v].setdefault(str(size), {})[str(s)] = r
                        log.info("curve: %s, %d poses, seed %d: test %.4f mm, front_check %.4f mm", v, size, s,
                                 next((x for k, x in r["test_3d_mae"].items() if k.startswith("spi_boter")), np.nan),
                                 r["validation"]["front_check"]["mean_3d_mm"]["model"])
                        rec["summary"] = curve_summary(rec["runs"])
                        rec["seconds"] = seconds0 + time.perf_counter() - t0
                        save(key, rec)
    return rec

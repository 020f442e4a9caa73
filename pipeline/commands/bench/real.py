"""`bench real`: the pipeline on one real set or the twin, per training seed; writes (and merges into)
reports/bench/real_data.json, a record per set (keyed `<set>@<overrides>` with -S), saved as each seed
finishes.

    python -m pipeline.commands.bench real  [--seeds 139 140 ...] [--engine ray]   the real sets in ../shared/datasets
    python -m pipeline.commands.bench real --sets twin twin-2stations   the twin, from one and two stations

It runs the pipeline's stages in this process (`pipeline.stages.run`, as dvc repro
would) in a scratch directory per set (preset merged over params.yaml, split
seed 7) and reports test 3D MAE for
nominal DH (no frame fit; only where the data are in the base frame), nominal
after the frame fit, classical calibration, the DNN baseline and SPI-BoTER
(on nominal and on calibrated physics), mean ± std over the training seeds,
and the seeds' SPI-BoTER models averaged (an ensemble); and, per seed, every
`validate.campaigns` entry of the preset (e.g. ipa-ur10's Series_B): mean 3D
error per method on the judged points, inside and outside the trained workspace;
and each training campaign's test 3D MAE per method (ipa-ur10-cb: Series_C and
Series_B trained together).

The stages up to parts run once per set, here; every seed is then a job (lib/learning/sweep.py) that
carries the prepared directory as bytes (with the campaigns' input files under inputs/; on Ray in
the object store, once per node), so Ray's nodes need no shared filesystem.
"""
import copy
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline import stages
from pipeline.commands.bench.common import BENCH, DATASETS, ROOT
from pipeline.lib.learning import sweep
from pipeline.lib.learning.metrics import seed_std
from pipeline.lib.learning.training import independent_seeds
from pipeline.lib.project.artifacts import (INGEST_JSON, INGEST_TABLE, METRICS_JSON, PARAMS_FILE, PREDICTIONS_TABLE,
                                            VALIDATION_DIR)
from pipeline.lib.project.columns import JOINTS_DEG, MEAS, PRED
from pipeline.lib.project.config import load_params, logger, read_json, write_json, yaml_text, yaml_values
from pipeline.lib.reading.prepared import load_prepared
from pipeline.lib.reading.presets import merged_params
from pipeline.lib.robot.kinematics import fk_numpy
from pipeline.lib.robot.robots import load_robot
from pipeline.lib.sim.twin import SEED
from pipeline.lib.sim.twin_files import generate

log = logger(__name__)
# name: the preset merged over params.yaml (None: params.yaml, the twin), the dataset it needs under
# ../shared/datasets (None: the committed twin campaigns), and whether its positions are already
# in the robot's base frame (then nominal DH is also judged without a frame fit)
REAL_SETS = {"gtpn-ur5": {"preset": "gtpn-ur5", "dataset": "gtpn-ur5", "base_frame": True},
             "ipa-ur10": {"preset": "ipa-ur10", "dataset": "ipa-ur10", "base_frame": False},
             "ipa-ur10-cb": {"preset": "ipa-ur10-cb", "dataset": "ipa-ur10", "base_frame": False},
             "twin": {"preset": None, "dataset": None, "base_frame": False},
             # the twin before issue 22 (no fine angular structure in its joints): its campaign made here
             "twin-nofine": {"preset": None, "dataset": None, "base_frame": False, "twin_fine": False},
             "twin-2stations": {"preset": "twin-2stations", "dataset": None, "base_frame": False}}


def absolute_paths(params: dict) -> dict:
    """Input paths of the ingest section made absolute (from the project root)."""
    p = copy.deepcopy(params)
    for ingest in ([p["ingest"]] + [c["ingest"] for c in (p["validate"]["campaigns"] or {}).values()]
                   + [c["ingest"] for c in (p["campaigns"]["more"] or {}).values()]):
        for k in ("joints", "tracker"):
            ingest[k] = str((ROOT / ingest[k]).resolve())
    p["compensate"]["drive_check"] = False
    p["compensate"]["twin"] = str((ROOT / p["compensate"]["twin"]).resolve())     # validate reads its record
    return p


def stage(name: str, params: dict, root: Path, *args: str) -> None:
    """One stage in this process on the project at `root`, on `params` written to its params.yaml, as
    dvc repro would run it there."""
    (root / PARAMS_FILE).write_text(yaml_text(params))
    stages.run(name, args, root)


def validation_runs(params: dict, root: Path) -> dict:
    """Every validate campaign of params, judged with the current models: mean 3D error per method
    (all judged points, and inside / outside the trained workspace)."""
    out = {}
    for name in params["validate"]["campaigns"] or {}:
        stages.run("validate", ["campaign", name], root)
        v = read_json(root / VALIDATION_DIR / f"{name}.json")
        out[name] = {"n_judged": v["n_judged"], "frame": v["frame"], "in_workspace_share": v["in_workspace_share"],
                     "mean_3d_mm": v["mean_3d_mm"], "angle_map_in_range_share": v["angle_map"]["in_range_share"],
                     "uncertainty_coverage": v["uncertainty_coverage"]["all"],
                     **{f"mean_3d_mm_{w}": {m: s["mean"] for m, s in v["by_workspace"][w].items()}
                        for w in ("in", "out")},
                     **{f"mean_3d_mm_map_{w}": {m: s["mean"] for m, s in v["angle_map"][w].items()}
                        for w in ("in", "out")},
                     **({"pose": pose_means(v["pose"])} if "pose" in v else {})}
    return out


def pose_means(pose: dict) -> dict:
    """{method: {orientation_arcsec, orientation_p95_arcsec, tcp_mm: {name: mean}}} of a pose record
    (evaluate's split or validate's campaign, lib/robot/tcp.py pose_errors), where orientation was measured."""
    return {m: {"orientation_arcsec": r["orientation"]["mean_arcsec"], "orientation_p95_arcsec":
                r["orientation"]["p95_arcsec"], "tcp_mm": {k: t["mean_mm"] for k, t in r["tcp"].items()}}
            for m, r in pose.items()}


def overridden(params: dict, overrides: list[str]) -> dict:
    """params with KEY=VALUE overrides applied (dotted keys, YAML values), as `dvc exp run -S`."""
    p = copy.deepcopy(params)
    for o in overrides:
        key, sep, value = o.partition("=")
        *path, last = key.split(".")
        node = p
        for k in path:
            node = node.get(k) if isinstance(node, dict) else None
        if not sep or not isinstance(node, dict) or last not in node:
            raise ValueError(f"bench -S {o!r}: not KEY=VALUE with KEY an existing params.yaml key")
        node[last] = yaml_values(value, f"bench -S {o!r}")
    return p


def seed_run(job, files: dict) -> dict:
    """One training seed of a set (a sweep job): the prepared directory (ingest .. parts done, the
    campaigns' input files under inputs/; lib/learning/sweep.py's pack: it travels as bytes, in Ray's object
    store once per node) unpacked to a scratch directory; there train, baselines, evaluate and every
    validate campaign, in this process."""
    p, test_ids = job
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        sweep.unpack(files, root)
        for name in ("train", "baselines", "evaluate"):
            stage(name, p, root)
        valid = validation_runs(p, root)
        metrics = read_json(root / METRICS_JSON)
        pred = pd.read_parquet(root / PREDICTIONS_TABLE).set_index("point_id").loc[test_ids][PRED].to_numpy()
    return {"runs": {k: v["test"]["3d"]["mae"] for k, v in metrics["baselines"].items()},
            "per_campaign": {c: {k: v[k]["test"]["mae"] for k in v if k not in ("station", "n")}
                             for c, v in metrics["campaigns"].items()},
            "valid": valid, "pred": pred,
            "pose": pose_means({m: r["test"] for m, r in metrics.get("pose", {}).items() if "test" in r})}


def localized(params: dict, folder: Path) -> dict:
    """params with every campaign's input files (ingest, campaigns.more, validate.campaigns) copied to
    folder/inputs/ and their paths made relative to folder: the seeds' jobs carry them with the rest."""
    p = copy.deepcopy(params)
    ingests = ([("main", p["ingest"])] + [(n, c["ingest"]) for n, c in (p["campaigns"]["more"] or {}).items()]
               + [(n, c["ingest"]) for n, c in (p["validate"]["campaigns"] or {}).items()])
    for name, ingest in ingests:
        copied = {}                                   # one table holding joints and positions stays one file
        for k in ("joints", "tracker"):
            src = Path(ingest[k]).resolve()
            if src not in copied:
                copied[src] = Path("inputs", name, k + "_" + src.name)
                (folder / copied[src]).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(src, folder / copied[src])
            ingest[k] = copied[src].as_posix()
    return p


def run_set(name: str, seeds: list[int], epochs: int | None, other_physics: bool = True, dnn: bool = True,
            on_seed=None, overrides: list[str] = (), engine: str = "sequential", address: str | None = None,
            threads: int | None = None) -> dict:
    """The full pipeline on one real set, once per training seed: the stages up to calibrate once,
    then every seed a sweep job (lib/learning/sweep.py: in order, or Ray tasks; `threads` torch threads each,
    default every core in order, 1 on Ray).

    on_seed(partial summary of the seeds finished so far) is called as each seed finishes, so a long
    run that is stopped keeps them.
    """
    base, preset = load_params(ROOT / "params.yaml"), REAL_SETS[name]["preset"]
    params = absolute_paths(overridden(base if preset is None else merged_params(preset, base), overrides))
    if epochs:
        params["train"]["max_epochs"] = epochs
    threads = sweep.threads_per_job(engine, threads)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        if REAL_SETS[name].get("twin_fine") is False:   # the twin's campaigns without the fine structure
            generate(root / "twin", SEED, fine=False)
            for ingest in [params["ingest"]] + [c["ingest"] for c in params["validate"]["campaigns"].values()]:
                for k in ("joints", "tracker"):
                    ingest[k] = str(root / "twin" / Path(ingest[k]).relative_to(ROOT / "data/raw"))
            params["compensate"]["twin"] = str(root / "twin/twin.json")
        for campaign in params["campaigns"]["more"] or {}:
            stage("ingest", params, root, "campaign", campaign)
        for name_ in ("ingest", "frame", "theory", "split", "calibrate", "parts"):
            stage(name_, params, root)
        n_kept = read_json(root / INGEST_JSON)["n_kept"]
        df = load_prepared(params["robot"], root, parts=False).points
        test = df[df.split == "test"]
        raw = pd.read_parquet(root / INGEST_TABLE).set_index("point_id").loc[test.point_id]
        nominal = None
        if REAL_SETS[name]["base_frame"]:             # no frame fit: measured as recorded
            robot = load_robot(params["robot"])
            e = fk_numpy(raw[JOINTS_DEG].to_numpy(), robot) - raw[MEAS].to_numpy()
            nominal = float(np.linalg.norm(e, axis=1).mean())
        local = localized(params, root)
        prepared_files = sweep.pack(root)                # the prepared directory, a value: no shared filesystem
        independent_seeds(seeds, local["train"]["members"], "bench real --seeds")
        jobs = []
        for i, seed in enumerate(seeds):
            p = copy.deepcopy(local)
            p["model"]["init_seed"], p["train"]["seed"] = seed, seed
            p["baselines"]["dnn"] = dnn
            p["baselines"]["other_physics"] = other_physics and i == 0   # first seed only
            jobs.append((p, list(test.point_id)))
        done = {}

        def summary(finished: dict) -> dict:
            order = sorted(finished)
            r = [finished[i] for i in order]
            # the seeds' models averaged: a deep ensemble (n times the cost of one model)
            ensemble = float(np.linalg.norm(np.mean([x["pred"] for x in r], 0) - test[MEAS].to_numpy(),
                                            axis=1).mean())
            return set_summary([x["runs"] for x in r], [x["valid"] for x in r], [x["per_campaign"] for x in r],
                               ensemble, [seeds[i] for i in order], n_kept, nominal, params, t0,
                               [x["pose"] for x in r])

        def finished(i, r):
            done[i] = r
            if on_seed:
                on_seed({**summary(done), "engine": engine, "threads_per_seed": threads})
        try:
            sweep.run(seed_run, jobs, engine, address, threads, desc=f"{name} seeds", on_result=finished,
                      shared=prepared_files)
        except sweep.SweepFailed as e:        # the other seeds finished: saved, with the failed ones named
            failed = [{"seed": seeds[i], "error": err} for i, _, err in e.failures]
            if on_seed and done:
                on_seed({**summary(done), "engine": engine, "threads_per_seed": threads, "failed": failed})
            raise sweep.SweepFailed(f"bench real {name} (seeds {[f['seed'] for f in failed]} failed)", e.failures,
                                    e.results, e.timing) from None
    return {**summary(done), "engine": engine, "threads_per_seed": threads}


def seed_stats(runs: list):
    """Each number of nested dicts of one shape (one per seed) as {mean, std, runs}."""
    if isinstance(runs[0], dict):
        return {k: seed_stats([r[k] for r in runs]) for k in runs[0]}
    return {"mean": float(np.mean(runs)), "std": seed_std(runs), "runs": runs}


def set_summary(runs: list[dict], valid: list[dict], per_campaign: list[dict], ensemble: float, seeds: list[int],
                n: int, nominal, params: dict, t0: float, poses: list[dict] | None = None) -> dict:
    per = {k: [r[k] for r in runs if k in r] for k in runs[0]}
    out = {"n": n, "seeds": seeds, "physics": params["model"]["physics"], "seconds": time.perf_counter() - t0,
           "max_epochs": params["train"]["max_epochs"], "train": params["train"],
           "fade_to": params["model"]["fade_to"]}
    validation = {}
    stat = lambda f, r: None if None in r else float(f(r))            # None: no point in that part
    for c in valid[0]:                      # per campaign and method: mean, std and every seed
        validation[c] = {k: valid[0][c][k] for k in ("n_judged", "frame", "in_workspace_share",
                                                     "angle_map_in_range_share")}
        validation[c]["uncertainty_coverage_runs"] = [v[c]["uncertainty_coverage"] for v in valid]
        for key in ("mean_3d_mm", "mean_3d_mm_in", "mean_3d_mm_out", "mean_3d_mm_map_in", "mean_3d_mm_map_out"):
            runs_ = {m: [v[c][key][m] for v in valid] for m in valid[0][c][key]}
            validation[c][key] = {m: stat(np.mean, r) for m, r in runs_.items()}
            validation[c][key + "_std"] = {m: None if None in r else seed_std(r) for m, r in runs_.items()}
            validation[c][key + "_runs"] = runs_
        if "pose" in valid[0][c]:             # orientation and TCP errors, where the campaign measures them
            validation[c]["pose"] = seed_stats([v[c]["pose"] for v in valid])
    campaigns = {}                          # per training campaign and method: mean, std, every seed
    for c, methods in per_campaign[0].items():
        runs_ = {m: [p[c][m] for p in per_campaign] for m in methods}
        campaigns[c] = {m: {"mean": float(np.mean(r)), "std": seed_std(r), "runs": r} for m, r in runs_.items()}
    return {**out, **seed_summary(per, nominal, params["model"]["physics"]),
            "test_3d_mae_ensemble": {"spi_boter": ensemble, "models": len(runs)}, "validation": validation,
            "test_3d_mae_per_campaign": campaigns, **({"test_pose": seed_stats(poses)} if poses and poses[0] else {})}


def seed_summary(per: dict, nominal: float | None, physics: str) -> dict:
    """test_3d_mae: one number per method (mean over seeds); its std and every seed's value beside it.

    per = {method: [test 3D MAE per seed]} with evaluate's method names.
    """
    names = {"frame": "nominal_dh", "calibrated": "calibrated_dh", "parts": "calibrated_parts", "dnn": "dnn",
             "spi_boter": f"spi_boter_{physics}", "spi_boter_nominal": "spi_boter_nominal",
             "spi_boter_calibrated": "spi_boter_calibrated"}
    mae = {"nominal": nominal, **{k: float(np.mean(per[v])) for k, v in names.items() if per.get(v)}}
    return {"test_3d_mae": mae,
            "test_3d_mae_std": {k: seed_std(per[v]) for k, v in names.items() if per.get(v)},   # None: one seed
            "test_3d_mae_runs": {k: per[v] for k, v in names.items() if per.get(v)}}


def bench_real(seeds: list[int], epochs: int | None, only: list[str] | None, other_physics=True,
               overrides: list[str] = (), engine: str = "sequential", address: str | None = None,
               threads: int | None = None, dnn: bool = True) -> dict:
    out_path = BENCH / "real_data.json"
    out = read_json(out_path) if out_path.exists() else {}
    for name in only or [k for k, v in REAL_SETS.items() if v["dataset"]]:
        dataset = REAL_SETS[name]["dataset"]
        if dataset and not (DATASETS / dataset).is_dir():
            log.info("skipping %s: %s not found", name, DATASETS / dataset)
            out[name] = {"skipped": f"{DATASETS / dataset} not found"}
            continue
        key = name + ("@" + ",".join(overrides) if overrides else "")
        log.info("running the pipeline on %s with seeds %s", key, seeds)
        def save(partial, key=key):
            out[key] = partial
            write_json(out_path, out)
        out[key] = run_set(name, seeds, epochs, other_physics, dnn, on_seed=save, overrides=overrides,
                           engine=engine, address=address, threads=threads)
        log.info("%s: %s", key, out[key]["test_3d_mae"])
        write_json(out_path, out)
    write_json(out_path, out)
    return out

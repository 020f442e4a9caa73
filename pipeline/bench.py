"""Benchmarks, written as JSON under reports/bench/.

    python -m pipeline.bench real  [--seeds 139 140 ...] [--engine ray]   the real sets in ../shared/datasets
    python -m pipeline.bench real --sets twin twin-2stations   the twin, from one and two stations
    python -m pipeline.bench speed                          training, prediction, compensation timings
    python -m pipeline.bench serve [--clients 8 --calls 10000]   the compensation service under load
    python -m pipeline.bench sweep                          a reduced ablation, in order vs on a local Ray

`real` runs the pipeline's stages (`python -m pipeline.<stage>`, as dvc repro
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
"""
import argparse
import copy
import os
import platform
import resource
import runpy
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
import xmlrpc.client
from pathlib import Path

import numpy as np
import pandas as pd
import torch
import yaml

from .lib import sweep
from .lib.ablations import Job, train_one
from .lib.artifacts import (CALIBRATED_GEOMETRY, FRAME_JSON, INGEST_JSON, INGEST_TABLE, METRICS_JSON, MODEL_ONNX,
                            MODEL_WEIGHTS, POINTS_TABLE, SPLIT_TABLE, PREDICTIONS_TABLE, VALIDATION_DIR, load_points)
from .lib.columns import JOINTS_DEG, MEAS, PRED, TARGET, THEORY
from .lib.config import load_params, logger, read_json, write_json
from .lib.geometry import Calibration, aligned, physics_geometry, theory_geometry
from .lib.kinematics import fk_numpy
from .lib.loss import SPILoss
from .lib.onnx_model import OnnxModel
from .lib.presets import merged_params
from .lib.realtime import Realtime, check
from .lib.robots import load_robot
from .lib.solvers import compensate
from .lib.training import fit, load_model, make_model, tensors

log = logger(__name__)
ROOT = Path(__file__).resolve().parents[1]
DATASETS = ROOT.parent / "shared" / "datasets"
BENCH = ROOT / "reports" / "bench"
# name: the preset merged over params.yaml (None: params.yaml, the twin), the dataset it needs under
# ../shared/datasets (None: the committed twin campaigns), and whether its positions are already
# in the robot's base frame (then nominal DH is also judged without a frame fit)
REAL_SETS = {"gtpn-ur5": {"preset": "gtpn-ur5", "dataset": "gtpn-ur5", "base_frame": True},
             "ipa-ur10": {"preset": "ipa-ur10", "dataset": "ipa-ur10", "base_frame": False},
             "ipa-ur10-cb": {"preset": "ipa-ur10-cb", "dataset": "ipa-ur10", "base_frame": False},
             "twin": {"preset": None, "dataset": None, "base_frame": False},
             "twin-2stations": {"preset": "twin-2stations", "dataset": None, "base_frame": False}}


def prepared(params: dict) -> tuple:
    """The pipeline's aligned points, calibration and nominal geometry, from the stage outputs here."""
    calibration = Calibration.from_dict(read_json(CALIBRATED_GEOMETRY))
    nominal = theory_geometry(load_robot(params["robot"]), read_json(FRAME_JSON)["tool_mm"])
    return aligned(load_points(), calibration, nominal), calibration, nominal


def absolute_paths(params: dict) -> dict:
    """Input paths of the ingest section made absolute (from the project root)."""
    p = copy.deepcopy(params)
    for ingest in ([p["ingest"]] + [c["ingest"] for c in (p["validate"]["campaigns"] or {}).values()]
                   + [c["ingest"] for c in (p["campaigns"]["more"] or {}).values()]):
        for k in ("joints", "tracker"):
            ingest[k] = str((ROOT / ingest[k]).resolve())
    p["compensate"]["drive_check"] = False
    return p


def stage(name: str, params: dict, *args: str) -> None:
    """Run one stage as dvc repro would, on params written to ./params.yaml."""
    Path("params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    subprocess.run([sys.executable, "-m", f"pipeline.{name}", *args], check=True)


def stage_here(name: str, *args: str) -> None:
    """Run one stage in this process as `python -m pipeline.<name> args` would (runpy: the module as
    __main__, on ./params.yaml): a sweep's run is then a Ray task with no subprocess."""
    argv = sys.argv
    sys.argv = [f"pipeline/{name}.py", *args]
    try:
        runpy.run_module(f"pipeline.{name}", run_name="__main__", alter_sys=True)
    finally:
        sys.argv = argv


def validation_runs(params: dict) -> dict:
    """Every validate campaign of params, judged with the current models: mean 3D error per method
    (all judged points, and inside / outside the trained workspace)."""
    out = {}
    for name in params["validate"]["campaigns"] or {}:
        stage_here("validate", "campaign", name)
        v = read_json(VALIDATION_DIR / f"{name}.json")
        out[name] = {"n_judged": v["n_judged"], "frame": v["frame"], "in_workspace_share": v["in_workspace_share"],
                     "mean_3d_mm": v["mean_3d_mm"],
                     **{f"mean_3d_mm_{w}": {m: s["mean"] for m, s in v["by_workspace"][w].items()}
                        for w in ("in", "out")}}
    return out


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
        node[last] = yaml.safe_load(value)
    return p


def seed_run(job) -> dict:
    """One training seed of a set (a sweep job): in a copy of the prepared directory (ingest ..
    calibrate done), train, baselines, evaluate and every validate campaign, in this process."""
    prepared, p, test_ids = job
    cwd = os.getcwd()
    with tempfile.TemporaryDirectory() as tmp:
        shutil.copytree(prepared, tmp, dirs_exist_ok=True)
        os.chdir(tmp)
        try:
            Path("params.yaml").write_text(yaml.safe_dump(p, sort_keys=False))
            for name in ("train", "baselines", "evaluate"):
                stage_here(name)
            valid = validation_runs(p)
            metrics = read_json(METRICS_JSON)
            pred = pd.read_parquet(PREDICTIONS_TABLE).set_index("point_id").loc[test_ids][PRED].to_numpy()
        finally:
            os.chdir(cwd)
    return {"runs": {k: v["test"]["3d"]["mae"] for k, v in metrics["baselines"].items()},
            "per_campaign": {c: {k: v[k]["test"]["mae"] for k in v if k not in ("station", "n")}
                             for c, v in metrics["campaigns"].items()},
            "valid": valid, "pred": pred}


def run_set(name: str, seeds: list[int], epochs: int | None, other_physics: bool = True,
            on_seed=None, overrides: list[str] = (), engine: str = "sequential", address: str | None = None,
            threads: int | None = None) -> dict:
    """The full pipeline on one real set, once per training seed: the stages up to calibrate once,
    then every seed a sweep job (lib/sweep.py: in order, or Ray tasks; `threads` torch threads each,
    default every core in order, 1 on Ray).

    on_seed(partial summary of the seeds finished so far) is called as each seed finishes, so a long
    run that is stopped keeps them.
    """
    base, preset = load_params(ROOT / "params.yaml"), REAL_SETS[name]["preset"]
    params = absolute_paths(overridden(base if preset is None else merged_params(preset, base), overrides))
    if epochs:
        params["train"]["max_epochs"] = epochs
    threads = sweep.threads_per_job(engine, threads)
    t0, cwd = time.perf_counter(), os.getcwd()
    with tempfile.TemporaryDirectory() as tmp:
        os.chdir(tmp)
        try:
            for campaign in params["campaigns"]["more"] or {}:
                stage("ingest", params, "campaign", campaign)
            for name_ in ("ingest", "frame", "theory", "split", "calibrate"):
                stage(name_, params)
            n_kept = read_json(INGEST_JSON)["n_kept"]
            df = prepared(params)[0]
            test = df[df.split == "test"]
            raw = pd.read_parquet(INGEST_TABLE).set_index("point_id").loc[test.point_id]
            nominal = None
            if REAL_SETS[name]["base_frame"]:             # no frame fit: measured as recorded
                robot = load_robot(params["robot"])
                e = fk_numpy(raw[JOINTS_DEG].to_numpy(), robot) - raw[MEAS].to_numpy()
                nominal = float(np.linalg.norm(e, axis=1).mean())
        finally:
            os.chdir(cwd)
        jobs = []
        for i, seed in enumerate(seeds):
            p = copy.deepcopy(params)
            p["model"]["init_seed"], p["train"]["seed"] = seed, seed
            p["baselines"]["dnn"] = True
            p["baselines"]["other_physics"] = other_physics and i == 0   # first seed only
            jobs.append((tmp, p, list(test.point_id)))
        done = {}

        def summary(finished: dict) -> dict:
            order = sorted(finished)
            r = [finished[i] for i in order]
            # the seeds' models averaged: a deep ensemble (n times the cost of one model)
            ensemble = float(np.linalg.norm(np.mean([x["pred"] for x in r], 0) - test[MEAS].to_numpy(),
                                            axis=1).mean())
            return set_summary([x["runs"] for x in r], [x["valid"] for x in r], [x["per_campaign"] for x in r],
                               ensemble, [seeds[i] for i in order], n_kept, nominal, params, t0)

        def finished(i, r):
            done[i] = r
            if on_seed:
                on_seed({**summary(done), "engine": engine, "threads_per_seed": threads})
        sweep.run(seed_run, jobs, engine, address, threads, desc=f"{name} seeds", on_result=finished)
    return {**summary(done), "engine": engine, "threads_per_seed": threads}


def set_summary(runs: list[dict], valid: list[dict], per_campaign: list[dict], ensemble: float, seeds: list[int],
                n: int, nominal, params: dict, t0: float) -> dict:
    per = {k: [r[k] for r in runs if k in r] for k in runs[0]}
    out = {"n": n, "seeds": seeds, "physics": params["model"]["physics"], "seconds": time.perf_counter() - t0,
           "max_epochs": params["train"]["max_epochs"], "train": params["train"],
           "fade_to": params["model"]["fade_to"]}
    validation = {}
    stat = lambda f, r: None if None in r else float(f(r))            # None: no point in that part
    for c in valid[0]:                      # per campaign and method: mean, std and every seed
        validation[c] = {k: valid[0][c][k] for k in ("n_judged", "frame", "in_workspace_share")}
        for key in ("mean_3d_mm", "mean_3d_mm_in", "mean_3d_mm_out"):
            runs_ = {m: [v[c][key][m] for v in valid] for m in valid[0][c][key]}
            validation[c][key] = {m: stat(np.mean, r) for m, r in runs_.items()}
            validation[c][key + "_std"] = {m: stat(np.std, r) for m, r in runs_.items()}
            validation[c][key + "_runs"] = runs_
    campaigns = {}                          # per training campaign and method: mean, std, every seed
    for c, methods in per_campaign[0].items():
        runs_ = {m: [p[c][m] for p in per_campaign] for m in methods}
        campaigns[c] = {m: {"mean": float(np.mean(r)), "std": float(np.std(r)), "runs": r} for m, r in runs_.items()}
    return {**out, **seed_summary(per, nominal, params["model"]["physics"]),
            "test_3d_mae_ensemble": {"spi_boter": ensemble, "models": len(runs)}, "validation": validation,
            "test_3d_mae_per_campaign": campaigns}


def seed_summary(per: dict, nominal: float | None, physics: str) -> dict:
    """test_3d_mae: one number per method (mean over seeds); its std and every seed's value beside it.

    per = {method: [test 3D MAE per seed]} with evaluate's method names.
    """
    names = {"frame": "nominal_dh", "calibrated": "calibrated_dh", "dnn": "dnn",
             "spi_boter": f"spi_boter_{physics}", "spi_boter_nominal": "spi_boter_nominal",
             "spi_boter_calibrated": "spi_boter_calibrated"}
    mae = {"nominal": nominal, **{k: float(np.mean(per[v])) for k, v in names.items() if per.get(v)}}
    return {"test_3d_mae": mae,
            "test_3d_mae_std": {k: float(np.std(per[v])) for k, v in names.items() if per.get(v)},
            "test_3d_mae_runs": {k: per[v] for k, v in names.items() if per.get(v)}}


def bench_real(seeds: list[int], epochs: int | None, only: list[str] | None, other_physics=True,
               overrides: list[str] = (), engine: str = "sequential", address: str | None = None,
               threads: int | None = None) -> dict:
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
        out[key] = run_set(name, seeds, epochs, other_physics, on_seed=save, overrides=overrides, engine=engine,
                           address=address, threads=threads)
        log.info("%s: %s", key, out[key]["test_3d_mae"])
        write_json(out_path, out)
    write_json(out_path, out)
    return out


def machine() -> dict:
    cpu = next((l.split(":", 1)[1].strip() for l in Path("/proc/cpuinfo").read_text().splitlines()
                if l.startswith("model name")), platform.processor()) if Path("/proc/cpuinfo").exists() else ""
    return {"cpu": cpu, "cores": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__, "python": platform.python_version(), "platform": platform.platform()}


def timed(fn, repeats: int) -> float:
    """Median wall time (s) of fn() over repeats, after one warm-up call."""
    fn()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


def bench_realtime(model, q0: np.ndarray, tgt: np.ndarray, limits: np.ndarray, tol_mm: float,
                   compiled: bool, repeats: int = 5) -> dict:
    """The controller path (realtime.py), one pose per call: latency over every target, repeats times."""
    t = time.perf_counter()
    rt = Realtime(model, limits, tol_mm, compile=compiled)
    setup = time.perf_counter() - t
    ms = []
    for _ in range(repeats):
        for a, b in zip(q0, tgt):
            t = time.perf_counter()
            rt(a, b)
            ms.append(1000 * (time.perf_counter() - t))
    return {"compiled": compiled, "setup_s": setup, "calls_timed": len(ms), "ms_median": float(np.median(ms)),
            "ms_p90": float(np.percentile(ms, 90)), "ms_p99": float(np.percentile(ms, 99)),
            "ms_max": float(np.max(ms)), **check(rt, q0, tgt)}


def bench_speed() -> dict:
    """Needs a finished `dvc repro` in the project (model, points, split)."""
    params = load_params()
    df, calibration, nominal = prepared(params)
    train_t, val_t = tensors(df[df.split == "train"]), tensors(df[df.split == "val"])
    model = make_model(params["model"], physics_geometry(params["model"]["physics"], calibration, nominal))
    cfg = {**params["train"], "max_epochs": 10, "patience": 10}
    hist = fit(model, SPILoss(**params["loss"]), train_t, val_t, cfg, progress=False)

    model = load_model(MODEL_WEIGHTS)
    q = torch.as_tensor(np.radians(np.random.default_rng(0).uniform(-3, 3, (4096, 6))), dtype=torch.float64)
    with torch.no_grad():
        batch_s = timed(lambda: model(q), 10)
        single_s = timed(lambda: model(q[:1]), 200)
    onnx = OnnxModel(MODEL_ONNX)                                       # the export stage's file, one thread
    q32 = q.float().numpy()
    onnx_batch_s, onnx_single_s = timed(lambda: onnx(q32), 10), timed(lambda: onnx(q32[:1]), 200)

    targets = pd.read_csv("reports/compensation.csv")                 # the compensate stage's targets
    q0, tgt = targets[JOINTS_DEG].to_numpy(), targets[TARGET].to_numpy()
    robot = load_robot(params["robot"])
    comp = {}
    for name, solver, jac in (("adam", "adam", None), ("lm", "lm", "physics"), ("lm_model_jacobian", "lm", "model")):
        cfg_c = {**params["compensate"], "jacobian_of": jac}
        _, pred, iters, ok, _, sec = compensate(model, q0, tgt, cfg_c, robot, solver)
        comp[name] = {"jacobian_of": jac, "n_points": len(q0), "seconds_all": sec,
                      "ms_per_point_batched": 1000 * sec / len(q0),
                      "iterations_mean": float(iters.mean()), "iterations_max": int(iters.max()),
                      "converged_share": float(ok.mean()),
                      "residual_mm_max": float(np.linalg.norm(pred - tgt, axis=1).max())}
    for name, jac in (("lm", "physics"), ("lm_model_jacobian", "model")):
        cfg_c = {**params["compensate"], "jacobian_of": jac}
        single = [timed(lambda i=i: compensate(model, q0[i:i + 1], tgt[i:i + 1], cfg_c, robot, "lm"), 5)
                  for i in range(min(20, len(q0)))]
        comp[name]["single_pose_ms_median"] = 1000 * float(np.median(single))
        comp[name]["single_pose_ms_max"] = 1000 * float(np.max(single))
    comp["iteration_ratio_adam_over_lm"] = comp["adam"]["iterations_mean"] / comp["lm"]["iterations_mean"]
    for name, compiled in (("realtime_eager", False), ("realtime", True)):
        comp[name] = bench_realtime(model, np.radians(q0), tgt, np.radians(robot.limits_deg),
                                    params["compensate"]["tol_mm"], compiled)
    out = {"machine": machine(),
           "train": {"n_train": len(train_t[0]), "seconds_per_epoch": hist["seconds_per_epoch"],
                     "epochs_timed": hist["epochs_run"], "model": params["model"]},
           "predict": {"batch": 4096, "poses_per_s": 4096 / batch_s, "single_pose_ms": 1000 * single_s,
                       "onnxruntime": {"poses_per_s": 4096 / onnx_batch_s, "single_pose_ms": 1000 * onnx_single_s,
                                       "single_pose_speedup_over_pytorch": single_s / onnx_single_s}},
           "compensate": comp,
           "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
    write_json(BENCH / "speed.json", out)
    log.info("predict one pose: PyTorch %.3f ms, onnxruntime %.3f ms", 1000 * single_s, 1000 * onnx_single_s)
    log.info("speed: %.3f s/epoch, %.0f poses/s (batch 4096), %.2f ms single pose; lm %.1f it vs adam %.1f it "
             "(%.0fx), lm single pose %.2f ms; realtime single pose %.2f ms median, %.2f ms p99 "
             "(eager %.2f ms), true residual max %.1e mm; peak RSS %.0f MB", hist["seconds_per_epoch"],
             out["predict"]["poses_per_s"], out["predict"]["single_pose_ms"], comp["lm"]["iterations_mean"],
             comp["adam"]["iterations_mean"], comp["iteration_ratio_adam_over_lm"],
             comp["lm"]["single_pose_ms_median"], comp["realtime"]["ms_median"], comp["realtime"]["ms_p99"],
             comp["realtime_eager"]["ms_median"], comp["realtime"]["true_residual_mm_max"], out["peak_rss_mb"])
    return out


def load_test(url: str, q0: list, tgt: list, clients: int, calls: int) -> dict:
    """`clients` threads, each with its own ServerProxy, make calls/clients `compensate` calls on the
    (q0, target) pairs (cycled); each call's wall latency."""
    ms, failed, unconverged = [[] for _ in range(clients)], [0] * clients, [0] * clients

    def client(k):
        proxy = xmlrpc.client.ServerProxy(url)
        for i in range(k, calls, clients):
            j = i % len(q0)
            t = time.perf_counter()
            try:
                unconverged[k] += not proxy.compensate(q0[j], tgt[j])["converged"]
            except Exception:
                failed[k] += 1
            ms[k].append(1000 * (time.perf_counter() - t))
    threads = [threading.Thread(target=client, args=(k,)) for k in range(clients)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    seconds, lat = time.perf_counter() - t0, np.concatenate(ms)
    return {"clients": clients, "calls": len(lat), "failed": sum(failed), "not_converged": sum(unconverged),
            "ms_p50": float(np.percentile(lat, 50)), "ms_p90": float(np.percentile(lat, 90)),
            "ms_p99": float(np.percentile(lat, 99)), "ms_max": float(lat.max()), "calls_per_s": len(lat) / seconds,
            "seconds": seconds}


def bench_serve(clients: int = 8, calls: int = 10000) -> dict:
    """The compensation service under load: `python -m pipeline.serve` in a subprocess on a free loopback
    port, eager and compiled (--compile); for each, one client (calls/10 calls: a call's own latency)
    then `clients` concurrent clients (calls in all), on the test points (recorded angles -> theory
    position, cycled). Needs a finished `dvc repro` in the project."""
    df = prepared(load_params())[0]
    test = df[df.split == "test"]
    q0, tgt = np.radians(test[JOINTS_DEG].to_numpy()).tolist(), test[THEORY].to_numpy().tolist()
    out = {"machine": machine(), "server": "python -m pipeline.serve, a subprocess on 127.0.0.1 (the clients "
                                           "on the same machine)", "n_test_points": len(q0)}
    for name, flag in (("eager", "--no-compile"), ("compiled", "--compile")):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        url = f"http://127.0.0.1:{port}/RPC2"
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "pipeline.serve", "--port", str(port), flag])
        try:
            while True:                                   # until it answers
                try:
                    xmlrpc.client.ServerProxy(url).system.listMethods()
                    break
                except OSError:
                    if proc.poll() is not None or time.perf_counter() - t0 > 120:
                        raise RuntimeError(f"python -m pipeline.serve did not start (exit code {proc.poll()})")
                    time.sleep(0.2)
            out[name] = {"startup_s": time.perf_counter() - t0,
                         "one_client": load_test(url, q0, tgt, 1, calls // 10),
                         "concurrent": load_test(url, q0, tgt, clients, calls)}
        finally:
            proc.terminate()
            proc.wait(timeout=30)
        for k in ("one_client", "concurrent"):
            r = out[name][k]
            log.info("serve %s, %d client(s): %d calls in %.1f s (%.0f calls/s), %d failed, %d not converged; "
                     "latency p50 %.1f ms, p90 %.1f ms, p99 %.1f ms, max %.1f ms", name, r["clients"], r["calls"],
                     r["seconds"], r["calls_per_s"], r["failed"], r["not_converged"], r["ms_p50"], r["ms_p90"],
                     r["ms_p99"], r["ms_max"])
    write_json(BENCH / "serve.json", out)
    return out


def noop(x):
    return x


def bench_sweep(groups=("baseline", "no_resnet"), seeds=(139, 140), epochs: int = 40) -> dict:
    """A reduced ablation (groups x seeds, `epochs` each) run sequentially (torch on every core) and as
    Ray tasks on a local Ray instance (one thread each, a task per core), on the project's trained
    artifacts copied to a scratch directory; and the per-task overhead Ray adds (trivial tasks).
    Needs a finished `dvc repro` in the project."""
    params = load_params()
    params["ablation"].update(seeds=list(seeds), max_epochs=epochs)
    cores = os.cpu_count() or 1
    df, calibration, nominal = prepared(params)
    p = {k: params[k] for k in ("model", "loss", "train", "workspace", "ablation")}
    jobs = [Job(df, {"calibrated": calibration.geometry, "nominal": nominal}, p, g, s) for g in groups for s in seeds]
    files = [POINTS_TABLE, SPLIT_TABLE, FRAME_JSON, CALIBRATED_GEOMETRY]
    out = {"machine": machine(), "what": f"ablation groups {list(groups)} x seeds {list(seeds)}, {epochs} epochs "
                                         "each (the full ablation: 8 groups x 5 seeds, up to 400 epochs)"}
    cwd = os.getcwd()
    with tempfile.TemporaryDirectory() as tmp:
        for f in files:
            (Path(tmp) / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(f, Path(tmp) / f)
        os.chdir(tmp)
        try:
            for engine, threads in (("sequential", cores), ("ray", 1)):
                runs, timing = sweep.run(train_one, jobs, engine, None, threads, desc=f"sweep {engine}")
                out[engine] = {**timing, "test_3d_mae": [r["test"]["3d"]["mae"] for r in runs]}
        finally:
            os.chdir(cwd)
    out["speedup_ray_over_sequential"] = out["sequential"]["seconds"] / out["ray"]["seconds"]
    n = 64
    _, seq = sweep.run(noop, list(range(n)), "sequential", desc="noop")
    t0 = time.perf_counter()
    sweep.run(noop, list(range(n)), "ray", desc="noop")
    with_startup = time.perf_counter() - t0
    import ray                                            # the same, Ray already up: the per-task cost alone
    ray.init(include_dashboard=False, log_to_driver=False, configure_logging=False,
             runtime_env={"env_vars": {"PYTHONPATH": str(sweep.PROJECT)}})
    try:
        sweep.run(noop, list(range(n)), "ray", desc="noop warm-up")
        _, warm = sweep.run(noop, list(range(n)), "ray", desc="noop")
    finally:
        ray.shutdown()
    out["overhead"] = {"tasks": n, "ray_seconds_with_startup": with_startup, "sequential_seconds": seq["seconds"],
                       "ms_per_task_after_startup": 1000 * warm["seconds"] / n,
                       "startup_s": with_startup - warm["seconds"]}
    write_json(BENCH / "sweep.json", out)
    log.info("sweep: sequential %.0f s, ray %.0f s (%.2fx); ray per task %.1f ms, startup %.1f s",
             out["sequential"]["seconds"], out["ray"]["seconds"], out["speedup_ray_over_sequential"],
             out["overhead"]["ms_per_task_after_startup"], out["overhead"]["startup_s"])
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m pipeline.bench", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["real", "speed", "serve", "sweep"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[139], help="training seeds (real)")
    ap.add_argument("--epochs", type=int, default=None, help="override train.max_epochs (real)")
    ap.add_argument("--sets", nargs="+", choices=list(REAL_SETS), default=None,
                    help="sets to run (default: the real ones; twin and twin-2stations on request)")
    ap.add_argument("--other-physics", action=argparse.BooleanOptionalAction, default=True,
                    help="also train SPI-BoTER on the other physics branch (first seed)")
    ap.add_argument("-S", "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override a params.yaml value for the run (real), as dvc exp run -S: "
                         "train.ema=0.999; recorded in the output under the set's name + '@' + overrides")
    ap.add_argument("--engine", choices=sweep.ENGINES, default="sequential",
                    help="real: the seeds in order, or as Ray tasks (lib/sweep.py)")
    ap.add_argument("--address", default=None, help="real: a Ray cluster (default: RAY_ADDRESS, else local)")
    ap.add_argument("--threads", type=int, default=None, help="real: torch threads per seed (default: every "
                                                              "core in order, 1 on Ray)")
    ap.add_argument("--clients", type=int, default=8, help="concurrent clients (serve)")
    ap.add_argument("--calls", type=int, default=10000, help="compensate calls in all (serve)")
    a = ap.parse_args(argv)
    if a.what == "real":
        bench_real(a.seeds, a.epochs, a.sets, a.other_physics, a.overrides, a.engine, a.address, a.threads)
    elif a.what == "serve":
        bench_serve(a.clients, a.calls)
    elif a.what == "sweep":
        bench_sweep()
    else:
        bench_speed()


if __name__ == "__main__":
    main()

"""`bench speed`: training seconds per epoch (10 epochs on the CPU; where torch sees a GPU, also 60 on it,
eager steps and one CUDA graph an epoch), prediction (PyTorch and onnxruntime, batch 4096 and
one pose), `lm` and `adam` compensation (batched and one pose), the controller path (realtime.py) eager and
compiled, and peak memory; writes reports/bench/speed.json. Needs a finished `dvc repro` in the project.

`controller` (issue 24): the controller path in PyTorch (eager, compiled) and on onnxruntime
(models/controller.onnx, OnnxRealtime), and on the model's physics branch alone (model.PhysicsOnly:
eager PyTorch, and models/controller_physics.onnx), timed alternating in one run on the same poses, so
that a load beside the benchmark falls on all five alike: call by call (the order rotating), and round by
round (a round over every pose by one path, then the next: caches warm): p50/p90/p99/p99.9/max and the
ratios; then `soak` seconds of each onnxruntime path alone (p50/p99/p99.9/max per window, and the drift:
the last window's p50 over the first's). `--only controller` runs just that part and replaces just those
keys of speed.json (each part records its machine).
"""
import gc
import resource
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from pipeline.commands.bench.common import BENCH, machine, timed
from pipeline.lib.learning.checkpoint import load_model, make_model
from pipeline.lib.learning.loss import SPILoss
from pipeline.lib.learning.model import PhysicsOnly
from pipeline.lib.learning.model import tensors
from pipeline.lib.learning.onnx_model import OnnxModel, OnnxRealtime, deviation
from pipeline.lib.learning.training import fit
from pipeline.lib.project.artifacts import CONTROLLER_ONNX, CONTROLLER_PHYSICS_ONNX, MODEL_ONNX, MODEL_WEIGHTS
from pipeline.lib.project.columns import JOINTS_DEG, TARGET
from pipeline.lib.project.config import load_params, logger, read_json, write_json
from pipeline.lib.reading.prepared import load_prepared
from pipeline.lib.robot.robots import load_robot
from pipeline.lib.runtime.realtime import Realtime, check
from pipeline.lib.runtime.solvers import compensate

log = logger(__name__)
PATHS = ("pytorch_eager", "pytorch_compiled", "onnx", "physics_pytorch", "physics_onnx")
OVER = {"onnx": ("pytorch_eager", "pytorch_compiled"),    # ratio_over_<name>: these paths' over its
        "physics_onnx": ("physics_pytorch", "onnx")}


def latency(ms) -> dict:
    """Percentiles (ms) of call latencies."""
    ms = np.asarray(ms)
    return {"calls": len(ms), "ms_p50": float(np.percentile(ms, 50)), "ms_p90": float(np.percentile(ms, 90)),
            "ms_p99": float(np.percentile(ms, 99)), "ms_p99_9": float(np.percentile(ms, 99.9)),
            "ms_max": float(ms.max()), "ms_mean": float(ms.mean())}


def bench_controller(model, q0: np.ndarray, tgt: np.ndarray, limits: np.ndarray, tol_mm: float, rounds: int = 20,
                     soak_s: float = 600.0, torch_threads: int = 1) -> dict:
    """The controller path, one pose per call, in PyTorch eager and compiled and on onnxruntime (the export
    stage's models/controller.onnx), and on the physics branch alone (PhysicsOnly: eager, and
    models/controller_physics.onnx): every call of the five interleaved (pose by pose, the order rotating),
    `rounds` times over the (q0, target) pairs, after one warm-up round; the answers compared; then the
    onnxruntime path alone for soak_s seconds, back to back, cycling the pairs. PyTorch on torch_threads
    threads (1, as onnxruntime: a controller's one core; with 2 on a busy 2-core machine its OpenMP workers
    wait on each other and on the load: eager p50 47 ms there, against 9 ms on 1)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(torch_threads)
    try:
        return _bench_controller(model, q0, tgt, limits, tol_mm, rounds, soak_s)
    finally:
        torch.set_num_threads(threads)


def _bench_controller(model, q0, tgt, limits, tol_mm, rounds, soak_s) -> dict:
    physics = PhysicsOnly(model)
    make = {"pytorch_eager": lambda: Realtime(model, limits, tol_mm),
            "pytorch_compiled": lambda: Realtime(model, limits, tol_mm, compile=True),
            "onnx": lambda: OnnxRealtime(CONTROLLER_ONNX, limits, tol_mm),
            "physics_pytorch": lambda: Realtime(physics, limits, tol_mm),
            "physics_onnx": lambda: OnnxRealtime(CONTROLLER_PHYSICS_ONNX, limits, tol_mm)}
    rts, setup = {}, {}
    for name in PATHS:
        t = time.perf_counter()
        rts[name] = make[name]()
        setup[name] = time.perf_counter() - t
    for rt in rts.values():                                            # warm-up
        for a, b in zip(q0, tgt):
            rt(a, b)
    out = {"project": str(Path.cwd()), "model_parameters": sum(p.numel() for p in model.parameters()),
           "n_poses": len(q0), "rounds": rounds, "threads": {"pytorch": torch.get_num_threads(), "onnxruntime": 1},
           "setup_s": setup}
    for mode in ("call", "round"):
        ms = interleaved(rts, q0, tgt, rounds, mode)
        r = {name: latency(ms[name]) for name in PATHS}
        for b, over in OVER.items():
            r[f"ratio_over_{b}"] = {a: {k: r[a][k] / r[b][k] for k in ("ms_p50", "ms_p99", "ms_p99_9")}
                                    for a in over}
        out[f"by_{mode}"] = r
    out["agreement_onnx_vs_pytorch"] = deviation(rts["pytorch_eager"], rts["onnx"], q0, tgt)
    out["agreement_physics_onnx_vs_pytorch"] = deviation(rts["physics_pytorch"], rts["physics_onnx"], q0, tgt)
    out["onnx_check"] = check(rts["onnx"], q0, tgt, model)
    out["physics_onnx_check"] = check(rts["physics_onnx"], q0, tgt, physics)
    out["soak"] = soak(rts["onnx"], q0, tgt, soak_s)
    out["soak_physics"] = soak(rts["physics_onnx"], q0, tgt, soak_s)
    return out


def interleaved(rts: dict, q0, tgt, rounds: int, mode: str) -> dict:
    """Call latencies (ms) of each path of rts, `rounds` times over the pairs, interleaved: mode "call", call
    by call (each pose by every path in turn, who goes first rotating: the same load on each, but each call
    finds the caches holding the others' weights), or "round", a round over all poses by one path, then the
    next (its caches warm, the load still shared over seconds)."""
    ms = {name: [] for name in rts}
    names = list(rts)
    for k in range(rounds):
        order = names[k % len(names):] + names[:k % len(names)]
        if mode == "call":
            calls = [(name, a, b) for j, (a, b) in enumerate(zip(q0, tgt))
                     for name in order[j % len(names):] + order[:j % len(names)]]
        else:
            calls = [(name, a, b) for name in order for a, b in zip(q0, tgt)]
        for name, a, b in calls:
            rt = rts[name]
            t = time.perf_counter()
            rt(a, b)
            ms[name].append(1000 * (time.perf_counter() - t))
    return ms


def soak(rt, q0: np.ndarray, tgt: np.ndarray, seconds: float) -> dict:
    """rt called back to back for `seconds`, cycling the pairs: latency per window (60 s, or seconds/5 when
    shorter), over all, and the drift (the last window's p50 over the first's; RSS before and after)."""
    window = min(60.0, seconds / 5)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    gc.collect()
    ms, at, i = [], [], 0
    start = time.perf_counter()
    while time.perf_counter() - start < seconds:
        a, b = q0[i % len(q0)], tgt[i % len(tgt)]
        i += 1
        t = time.perf_counter()
        rt(a, b)
        ms.append(1000 * (time.perf_counter() - t))
        at.append(t - start)
    ms, w = np.array(ms), (np.array(at) // window).astype(int)
    windows = [{"from_s": k * window, **latency(ms[w == k])} for k in range(w.max() + 1) if (w == k).sum() > 0]
    if len(windows) > 1 and windows[-1]["calls"] < 0.5 * windows[0]["calls"]:
        windows = windows[:-1]                                         # a last, cut-short window
    return {"seconds": seconds, "window_s": window, "all": latency(ms), "windows": windows,
            "drift_p50": windows[-1]["ms_p50"] / windows[0]["ms_p50"],
            "drift_p99": windows[-1]["ms_p99"] / windows[0]["ms_p99"],
            "max_rss_mb_before": rss0, "max_rss_mb_after": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def log_controller(c: dict) -> None:
    for mode in ("call", "round"):
        for name in PATHS:
            r = c[f"by_{mode}"][name]
            log.info("controller path, interleaved by %-5s %-16s p50 %.3f ms, p90 %.3f, p99 %.3f, p99.9 %.3f, "
                     "max %.3f (%d calls)", mode, name, r["ms_p50"], r["ms_p90"], r["ms_p99"], r["ms_p99_9"],
                     r["ms_max"], r["calls"])
        for b in OVER:
            for a, r in c[f"by_{mode}"][f"ratio_over_{b}"].items():
                log.info("  %s / %s: p50 %.2fx, p99 %.2fx, p99.9 %.2fx", a, b, r["ms_p50"], r["ms_p99"], r["ms_p99_9"])
    for name, key, soak_key in (("onnx", "agreement_onnx_vs_pytorch", "soak"),
                                ("physics_onnx", "agreement_physics_onnx_vs_pytorch", "soak_physics")):
        d, s = c[key], c[soak_key]
        log.info("%s vs its pytorch path, answers: max %.1e rad, residual %.1e mm, flags differ %d", name,
                 d["max_q_rad"], d["max_residual_mm"], d["flags_differ"])
        log.info("%s soak %.0f s (%d calls): p50 %.3f ms, p99 %.3f, p99.9 %.3f, max %.3f; drift p50 %.3f, p99 %.3f",
                 name, s["seconds"], s["all"]["calls"], s["all"]["ms_p50"], s["all"]["ms_p99"], s["all"]["ms_p99_9"],
                 s["all"]["ms_max"], s["drift_p50"], s["drift_p99"])
        for w in s["windows"]:
            log.info("  from %5.0f s: p50 %.3f ms, p99 %.3f, p99.9 %.3f, max %.3f", w["from_s"], w["ms_p50"],
                     w["ms_p99"], w["ms_p99_9"], w["ms_max"])


def controller_only(soak_s: float, rounds: int, torch_threads: int) -> dict:
    """`bench speed --only controller`: bench_controller on the compensate stage's targets; replaces the
    `controller` key of speed.json (with its machine), the rest of the file kept."""
    params = load_params()
    model = load_model(MODEL_WEIGHTS)
    targets = pd.read_csv("reports/compensation.csv")
    q0, tgt = np.radians(targets[JOINTS_DEG].to_numpy()), targets[TARGET].to_numpy()
    c = bench_controller(model, q0, tgt, np.radians(load_robot(params["robot"]).limits_deg),
                         params["compensate"]["tol_mm"], rounds, soak_s, torch_threads)
    path = BENCH / "speed.json"
    out = read_json(path) if path.exists() else {}
    out["controller"] = {"machine": machine(), **c}
    write_json(path, out)
    log_controller(c)
    return out


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


def bench_speed(soak_s: float = 600.0, rounds: int = 20, only: str | None = None, torch_threads: int = 1) -> dict:
    """Needs a finished `dvc repro` in the project (model, points, split)."""
    if only == "controller":
        return controller_only(soak_s, rounds, torch_threads)
    params = load_params()
    prep = load_prepared(params["robot"])
    df, geometries = prep.points, prep.geometries()
    train_t, val_t = tensors(df[df.split == "train"]), tensors(df[df.split == "val"])
    model = make_model(params["model"], geometries[params["model"]["physics"]])
    cfg = {**params["train"], "max_epochs": 10, "patience": 10, "device": "cpu"}
    hist = fit(model, SPILoss(**params["loss"]), train_t, val_t, cfg, progress=False)
    gpu = {}
    if torch.cuda.is_available():      # train.device cuda: eager steps against one CUDA graph an epoch
        for name, graphed in (("eager", False), ("graphed", True)):
            m = make_model(params["model"], geometries[params["model"]["physics"]])
            h = fit(m, SPILoss(**params["loss"]), train_t, val_t, {**cfg, "max_epochs": 60, "patience": 60,
                                                                    "device": "cuda"}, progress=False, graphed=graphed)
            gpu[name] = {"seconds_per_epoch": h["seconds_per_epoch"], "epochs_timed": h["epochs_run"],
                         "best_val_mae_3d_mm": h["best_val_mae_3d_mm"]}
        gpu["device"] = torch.cuda.get_device_name()
        gpu["speedup_graphed_over_cpu"] = hist["seconds_per_epoch"] / gpu["graphed"]["seconds_per_epoch"]

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
    controller = bench_controller(model, np.radians(q0), tgt, np.radians(robot.limits_deg),
                                  params["compensate"]["tol_mm"], rounds, soak_s, torch_threads)
    out = {"machine": machine(),
           "train": {"n_train": len(train_t[0]), "seconds_per_epoch": hist["seconds_per_epoch"],
                     "epochs_timed": hist["epochs_run"], "model": params["model"], "device": "cpu"},
           "train_cuda": gpu or "no CUDA GPU seen by torch: not measured",
           "predict": {"batch": 4096, "poses_per_s": 4096 / batch_s, "single_pose_ms": 1000 * single_s,
                       "onnxruntime": {"poses_per_s": 4096 / onnx_batch_s, "single_pose_ms": 1000 * onnx_single_s,
                                       "single_pose_speedup_over_pytorch": single_s / onnx_single_s}},
           "compensate": comp,
           "controller": {"machine": machine(), **controller},
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
    log_controller(controller)
    return out

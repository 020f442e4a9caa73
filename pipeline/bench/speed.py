"""`bench speed`: training seconds per epoch (10 epochs on the CPU; where torch sees a GPU, also 60 on it,
eager steps and one CUDA graph an epoch), prediction (PyTorch and onnxruntime, batch 4096 and
one pose), `lm` and `adam` compensation (batched and one pose), the controller path (realtime.py) eager and
compiled, and peak memory; writes reports/bench/speed.json. Needs a finished `dvc repro` in the project."""
import resource
import time

import numpy as np
import pandas as pd
import torch

from ..lib.artifacts import MODEL_ONNX, MODEL_WEIGHTS
from ..lib.columns import JOINTS_DEG, TARGET
from ..lib.config import load_params, logger, write_json
from ..lib.loss import SPILoss
from ..lib.onnx_model import OnnxModel
from ..lib.realtime import Realtime, check
from ..lib.robots import load_robot
from ..lib.solvers import compensate
from ..lib.training import fit, load_model, make_model, tensors
from .common import BENCH, machine, prepared, timed

log = logger(__name__)

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
    df, geometries = prepared(params)
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
    out = {"machine": machine(),
           "train": {"n_train": len(train_t[0]), "seconds_per_epoch": hist["seconds_per_epoch"],
                     "epochs_timed": hist["epochs_run"], "model": params["model"], "device": "cpu"},
           "train_cuda": gpu or "no CUDA GPU seen by torch: not measured",
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

"""Stage compensate: Δθ tables by inverting the frozen model (sec. 2.3, eq. 19).

For each target point, find joint angles θ whose predicted position hits the
target; start from the recorded angles. Two solvers, both batched over all
points:
  adam  the paper's: Adam on θ, lr 1e-4, ≤ 500 iterations, stop at MSE < 1e-4 mm²
        (each point stops on its own; Adam's update is per-coordinate, so one
        batched run equals independent runs).
  lm    damped Gauss-Newton / Levenberg-Marquardt on autograd Jacobians:
        Δθ = -Jᵀ (J Jᵀ + λI)⁻¹ r, the minimum-norm joint correction (3 equations,
        6 unknowns), λ adapted per point, joint limits respected, stop at
        |r| < tol_mm.
The Δθ table (DATA_FORMAT.md) comes from `compensate.solver`; both solvers
are run and their convergence recorded, and so is the controller path
(realtime.py: one pose per call, two model evaluations) on the same targets. On twin data the twin is driven to
the recorded and to the compensated angles and measured (the paper's Table 9).
"""
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from .columns import COMPENSATION, DJ_DEG, JCOMP_DEG, JOINTS_DEG, PRED, TARGET, THEORY
from .config import FRAME_JSON, REPORTS, load_params, logger, read_json, write_json
from .kinematics import DTYPE, fk_jacobian
from .metrics import drive_table
from .realtime import Realtime, check, min_norm_step
from .robots import load_robot
from .train import load_model, load_points

log = logger(__name__)


def predict(model, q):                                     # (B, 6) -> (B, 3)
    return model(q)[0]


def jacobian(f, q):
    """Batched Jacobian J (B, 3, 6) = df/dq of a function f: (B, 6) -> (B, 3).

    Each output row depends only on its own input row (eval mode), so the
    gradient of the batch sum of output k gives every point's row k at once.
    """
    q = q.detach().requires_grad_(True)
    p = f(q)
    rows = [torch.autograd.grad(p[:, k].sum(), q, retain_graph=k < 2)[0] for k in range(3)]
    return torch.stack(rows, 1)


def solve_adam(model, q0, target, lr=1e-4, max_iter=500, tol_mse=1e-4, **_):
    """The paper's procedure (sec. 2.3). Returns q, prediction, iterations, converged, history."""
    q = q0.clone().requires_grad_(True)
    opt = torch.optim.Adam([q], lr=lr)
    q_final, iters = q0.clone(), torch.full((len(q0),), max_iter)
    done = torch.zeros(len(q0), dtype=torch.bool)
    history = []
    for it in range(max_iter + 1):
        r = predict(model, q) - target
        mse = (r ** 2).mean(1)                              # (B,) per-point MSE, mm²
        history.append(r.detach().norm(dim=1))
        new = (mse < tol_mse).detach() & ~done
        q_final[new], iters[new] = q.detach()[new], it
        done |= new
        if done.all() or it == max_iter:
            break
        opt.zero_grad()
        mse.sum().backward()
        opt.step()
    q_final[~done] = q.detach()[~done]
    with torch.no_grad():
        pred = predict(model, q_final)
    return q_final, pred, iters, done, torch.stack(history)


def solve_lm(model, q0, target, max_iter=500, tol_mm=1e-3, limits=None, lam0=1e-3,
             jacobian_of="model", **_):
    """Batched Levenberg-Marquardt on the frozen model. Returns q, prediction, iterations, converged, history.

    jacobian_of: "model" differentiates the whole model by autograd; "physics"
    takes its DH branch's geometric Jacobian (kinematics.fk_jacobian: exact,
    float64, one FK pass), leaving out the network's small slope: each step is
    then a chord step, the residual always from the whole model.
    """
    if jacobian_of == "physics":
        jac = lambda q: fk_jacobian(q, model.physics.geometry())[1]
    else:
        jac = lambda q: jacobian(lambda x: predict(model, x), q)
    q = q0.clone()
    lam = torch.full((len(q0),), lam0, dtype=DTYPE)
    iters = torch.full((len(q0),), max_iter)
    done = torch.zeros(len(q0), dtype=torch.bool)
    with torch.no_grad():
        r = predict(model, q) - target                      # (B, 3) residual, mm
    err = r.norm(dim=1)
    history = [err.clone()]
    for it in range(max_iter):
        new = (err < tol_mm) & ~done
        iters[new] = it
        done |= new
        if done.all():
            break
        a = (~done).nonzero().squeeze(1)                    # active points
        J = jac(q[a])                                       # (A, 3, 6)
        q_try = q[a] + min_norm_step(J, r[a], lam[a])       # (A, 6)
        if limits is not None:
            q_try = q_try.clamp(limits[:, 0], limits[:, 1])
        with torch.no_grad():
            r_try = predict(model, q_try) - target[a]
        ok = r_try.norm(dim=1) < err[a]
        q[a[ok]], r[a[ok]] = q_try[ok], r_try[ok]
        err[a[ok]] = r_try[ok].norm(dim=1)
        lam[a] = torch.where(ok, lam[a] / 3, lam[a] * 10)
        history.append(err.clone())
    else:
        new = (err < tol_mm) & ~done
        iters[new] = max_iter
        done |= new
    return q, r + target, iters, done, torch.stack(history)


SOLVERS = {"adam": solve_adam, "lm": solve_lm}


def compensate(model, q0_deg: np.ndarray, target: np.ndarray, cfg: dict, robot=None, solver=None):
    """Solve for every point; returns (q_deg (n, 6), pred (n, 3), iterations, converged, history, seconds)."""
    solver = solver or cfg["solver"]
    if solver not in SOLVERS:
        raise ValueError(f"params.yaml compensate.solver: unknown {solver!r}; use one of {sorted(SOLVERS)}")
    for p in model.parameters():
        p.requires_grad_(False)                             # Step 1: freeze
    model.eval()
    limits = None if robot is None else torch.as_tensor(np.radians(robot.limits_deg), dtype=DTYPE)
    q0 = torch.as_tensor(np.radians(q0_deg), dtype=DTYPE)
    tgt = torch.as_tensor(target, dtype=DTYPE)
    t0 = time.perf_counter()
    q, pred, iters, ok, hist = SOLVERS[solver](model, q0, tgt, limits=limits, **cfg)
    seconds = time.perf_counter() - t0
    return np.degrees(q.numpy()), pred.numpy(), iters.numpy(), ok.numpy(), hist.numpy(), seconds


def load_targets(params: dict) -> pd.DataFrame:
    """point_id, j1_deg..j6_deg, target_x..z: every test point (target = its theory position,
    base frame) or the user's CSV from compensate.targets."""
    path = params["compensate"].get("targets")
    if path:
        df = pd.read_csv(path)
        missing = [c for c in ["point_id"] + JOINTS_DEG + TARGET if c not in df.columns]
        if missing:
            raise ValueError(f"{path}: missing column(s) {missing}; found {list(df.columns)}")
        return df
    df = load_points()
    df = df[df.split == "test"].reset_index(drop=True)
    return df[["point_id"] + JOINTS_DEG].assign(**dict(zip(TARGET, df[THEORY].to_numpy().T)))


def drive_check(params: dict, q_before: np.ndarray, q_after: np.ndarray, target: np.ndarray):
    """Drive the twin to the recorded and compensated angles, measure, map to base; Table 9 stats."""
    from .theory import to_base
    from .twin import Twin
    twin = Twin.from_json(params["compensate"]["twin"])
    frame = read_json(FRAME_JSON)
    rng = np.random.default_rng(params["compensate"]["drive_seed"])
    before = to_base(twin.drive(q_before, rng), frame)
    after = to_base(twin.drive(q_after, rng), frame)
    errors = np.hstack([before - target, after - target])  # (n, 6) achieved - target, mm
    cols = [f"{w}_{a}" for w in ("before", "after") for a in "xyz"]
    return {"before": drive_table(before, target), "after": drive_table(after, target),
            "noise_floor_mm": twin.noise_floor_mm}, pd.DataFrame(errors, columns=cols)


def run(params: dict) -> dict:
    cfg = params["compensate"]
    robot = load_robot(params["robot"])
    model = load_model(params)
    df = load_targets(params)
    q0, target = df[JOINTS_DEG].to_numpy(), df[TARGET].to_numpy()
    summary, histories = {"solver": cfg["solver"], "n_points": len(df)}, {}
    for solver in SOLVERS:                                  # both, for the comparison; table from cfg
        q, pred, iters, ok, hist, sec = compensate(model, q0, target, cfg, robot, solver)
        res = np.linalg.norm(pred - target, axis=1)
        histories[solver] = hist
        summary[solver] = {"converged_share": float(ok.mean()), "iterations_mean": float(iters.mean()),
                           "iterations_max": int(iters.max()), "residual_mm_mean": float(res.mean()),
                           "residual_mm_max": float(res.max()), "seconds": sec,
                           "ms_per_point": 1000 * sec / len(df)}
        log.info("%s: %d points, %.0f%% converged, %.1f iterations on average (max %d), "
                 "residual mean %.2e mm max %.2e mm, %.3f s", solver, len(df), 100 * ok.mean(),
                 iters.mean(), iters.max(), res.mean(), res.max(), sec)
        if solver == cfg["solver"]:
            table = df[["point_id"] + JOINTS_DEG].copy()
            table[DJ_DEG] = q - q0                          # eq. 19, degrees
            table[JCOMP_DEG] = q
            table[TARGET], table[PRED] = target, pred
            table["residual_mm"], table["iterations"], table["converged"] = res, iters, ok
    rt = Realtime(model, np.radians(robot.limits_deg), cfg["tol_mm"])   # the controller path, same targets
    summary["realtime"] = check(rt, np.radians(q0), target)
    log.info("realtime (one pose per call, 2 model evaluations): %.0f%% verified, %.0f%% converged, "
             "residual max %.2e mm", 100 * summary["realtime"]["verified_share"],
             100 * summary["realtime"]["converged_share"], summary["realtime"]["true_residual_mm_max"])
    table = table[COMPENSATION]
    table.to_csv(REPORTS / "compensation.csv", index=False, float_format="%.6f")
    table.to_parquet(REPORTS / "compensation.parquet", index=False)
    save_convergence(histories)
    errors = pd.DataFrame(columns=["point_id"] + [f"{w}_{a}" for w in ("before", "after") for a in "xyz"])
    if cfg.get("twin") and Path(cfg["twin"]).exists() and not cfg.get("targets"):
        summary["drive_check"], errors = drive_check(params, q0, table[JCOMP_DEG].to_numpy(), target)
        errors.insert(0, "point_id", table["point_id"])
        b, a = summary["drive_check"]["before"], summary["drive_check"]["after"]
        log.info("twin drive check on %d points: 3D error mean %.4f -> %.4f mm, max %.4f -> %.4f mm, "
                 "within ±%.1f mm %.0f%% -> %.0f%%", a["n"], b["3d"]["mean"], a["3d"]["mean"],
                 b["3d"]["max"], a["3d"]["max"], a["tol_mm"], 100 * b["within_tol_share"],
                 100 * a["within_tol_share"])
    errors.to_csv(REPORTS / "drive_check.csv", index=False, float_format="%.6f")   # empty: no twin
    write_json(REPORTS / "compensation.json", summary)
    return summary


def save_convergence(histories: dict) -> None:
    """Residual (max and mean over points, mm) per iteration and solver, for the plots."""
    rows = [{"solver": s, "iteration": i, "max_residual_mm": float(h[i].max()),
             "mean_residual_mm": float(h[i].mean())} for s, h in histories.items() for i in range(len(h))]
    pd.DataFrame(rows).to_csv(REPORTS / "compensation_convergence.csv", index=False)


def main():
    run(load_params())


if __name__ == "__main__":
    main()

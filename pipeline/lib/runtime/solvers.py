"""Compensation: joint angles that put the model's prediction on a target (sec. 2.3, eq. 19).

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
A target is a position (B, 3) mm, or a pose (B, 12): the position and the flange's orientation
(3×3, row-major, base frame). A pose adds three equations (six for six joints): the orientation
error e (rad, kinematics.rotation_error of the physics branch's flange, the network corrects
positions only), weighted by w = tol_mm / tol_arcsec (in rad) so that |[r, w e]| < tol_mm holds
both to their tolerances (`residual`, `pose_weight`).
`min_norm_step` is the damped minimum-norm step both `lm` and the controller
path (realtime.py: two model evaluations a pose) take; `lm_step`, one lm
iteration, is also what the service (service.py) resumes request by request.
"""
import os
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from pipeline.lib.project.config import logger
from pipeline.lib.robot.kinematics import (DTYPE, angular_jacobian, cross, fk_jacobian, fk_pose_jacobian,
                                           flange_rotations, rotation_error)

log = logger(__name__)


def min_norm_step(J, r, lam):
    """Damped minimum-norm joint correction Δθ = -Jᵀ (J Jᵀ + λ·mean(diag J Jᵀ)·I)⁻¹ r.

    J (B, m, 6) mm/rad, r (B, m) mm (m = 3, or 6 for a pose), lam (B,) or a float -> Δθ (B, 6) rad.
    Shared by the batched lm (λ adapted per point) and the controller path (realtime.py, λ tiny, fixed).
    """
    JJt = J @ J.transpose(1, 2)                             # (B, m, m)
    scale = torch.as_tensor(lam, dtype=DTYPE) * JJt.diagonal(dim1=1, dim2=2).mean(1)   # (B,)
    damped = JJt + scale[:, None, None] * torch.eye(J.shape[1], dtype=DTYPE)
    if torch.compiler.is_exporting():                      # ONNX has no linear solve: the closed forms
        x = solve3(damped, r) if J.shape[1] == 3 else solve_spd(damped, r)
    else:
        x = torch.linalg.solve(damped, r.unsqueeze(-1)).squeeze(-1)
    return -(J.transpose(1, 2) @ x.unsqueeze(-1)).squeeze(-1)


def solve3(A, b):
    """x = A⁻¹ b for 3×3 systems A (B, 3, 3), b (B, 3), in closed form (what the ONNX export runs for
    torch.linalg.solve): with A's columns a0, a1, a2, the rows of A⁻¹ are a1×a2, a2×a0, a0×a1 over
    det A = a0 · (a1×a2). On the damped J Jᵀ of a chord step it agrees with LAPACK's LU to ~1e-13
    relative (tests/test_compensate.py)."""
    a0, a1, a2 = A[..., 0], A[..., 1], A[..., 2]           # (B, 3) columns
    rows = torch.stack([cross(a1, a2), cross(a2, a0), cross(a0, a1)], 1)   # (B, 3, 3): det · A⁻¹
    return (rows @ b.unsqueeze(-1)).squeeze(-1) / (a0 * rows[:, 0]).sum(-1, keepdim=True)


def solve_spd(A, b):
    """x = A⁻¹ b for symmetric positive definite systems A (B, m, m), b (B, m) by Gaussian elimination
    without pivoting, unrolled (what the ONNX export runs for a pose's 6×6 damped J Jᵀ: stable without
    pivots on SPD, as Cholesky is). Agrees with LAPACK to ~1e-12 relative on the chord step's systems
    (tests/test_export.py)."""
    m = A.shape[-1]
    A, b = A.clone(), b.clone()
    for k in range(m):                                      # eliminate column k below the diagonal
        f = A[:, k + 1:, k] / A[:, k:k + 1, k]              # (B, m-k-1)
        A = torch.cat([A[:, :k + 1], A[:, k + 1:] - f[..., None] * A[:, k:k + 1]], 1)
        b = torch.cat([b[:, :k + 1], b[:, k + 1:] - f * b[:, k:k + 1]], 1)
    x = []
    for k in reversed(range(m)):                            # back substitution
        s = b[:, k] - sum(A[:, k, j] * x[m - 1 - j] for j in range(k + 1, m)) if k < m - 1 else b[:, k]
        x.append(s / A[:, k, k])
    return torch.stack(x[::-1], 1)


EVAL_ROWS = 256                     # rows the model evaluates at once: they stay in the cache (a 4096-row batch
                                    # costs 1.3-1.5x as much a row, docs/decisions.md), the same numbers


def predict(model, q):                                     # (B, 6) -> (B, 3), EVAL_ROWS rows at a time
    if len(q) <= EVAL_ROWS:
        return model(q)[0]
    return torch.cat([model(q[s])[0] for s in slices(len(q), EVAL_ROWS)])


def pose_weight(cfg: dict) -> float:
    """w (mm/rad): the orientation error's weight in a pose's residual, tol_mm over tol_arcsec in rad."""
    return cfg["tol_mm"] / np.radians(cfg["tol_arcsec"] / 3600)


def physics_rows(q, g: dict, rot=None, w: float | None = None, flange: bool = False):
    """The physics branch (geometry g) at q (B, 6), one FK pass: its marker position p (B, 3), the Jacobian a
    step solves with and the orientation's residual rows: J (B, 3, 6) and None; for a pose (rot (B, 3, 3), w)
    `pose_jacobian`'s [J; w Jω] (B, 6, 6) and `pose_residual`'s rows w e (B, 3), to the bit; flange: the
    flange's R (B, 3, 3) fourth (a pose's)."""
    if rot is None:
        return *fk_jacobian(q, g), None
    p, J, R, Jw = fk_pose_jacobian(q, g)
    rows = (p, torch.cat([J, w * Jw], 1), w * rotation_error(R, rot))
    return (*rows, R) if flange else rows


def with_orientation(r, e):
    """A step's residual: the position's r (B, 3), with the orientation's rows e (B, 3) below when given."""
    return r if e is None else torch.cat([r, e], 1)


def residual(model, q, target, w: float):
    """The residual lm and adam drive to zero: (B, 6) rad, target (B, 3) -> (B, 3) mm, the model's
    position minus the target; a pose target (B, 12) -> (B, 6), with w e appended (e: the physics
    branch's flange orientation against the target's, rad)."""
    r = predict(model, q) - target[:, :3]
    if target.shape[1] == 3:
        return r
    return pose_residual(r, q, model.physics.geometry(), target_rotations(target), w)


def position_error(r):                                     # (B, 3|6) -> (B,): |pred - target| mm, a pose's too
    return r[:, :3].norm(dim=1)


def target_rotations(target):                              # (B, 12) -> (B, 3, 3): a pose target's orientation
    return target[:, 3:].reshape(-1, 3, 3)


def orientation_residual(g: dict, q, target):              # (B, 6), (B, 12) -> (B, 3) rad
    return rotation_error(flange_rotations(q, g), target_rotations(target))


def orientation_angle(g: dict, q, target):                 # (B, 6), (B, 12) -> (B,) rad, in [0, π]
    """The flange's whole rotation angle off a pose target's orientation: atan2(|sin θ axis|, cos θ). Not the
    residual's |e| (`rotation_error`: sin θ, zero again at θ = 180°, so a flange turned half round would pass
    as reached): what `converged` and the reported orientation residual are judged by."""
    R, T = flange_rotations(q, g), target_rotations(target)
    return torch.atan2(rotation_error(R, T).norm(dim=-1), cos_angle(R, T))


def cos_angle(R, T):                                       # (B, 3, 3) x2 -> (B,)
    """cos θ of the rotation between R and T: (trace(R Tᵀ) - 1) / 2."""
    return ((R @ T.transpose(-1, -2)).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2


def pose_residual(r, q, g: dict, rot, w: float):
    """A pose's residual [r; w e] (B, 6): the position's r (B, 3) mm and the flange's orientation error e
    (B, 3) rad at q (B, 6) under geometry g against rot (B, 3, 3), weighted by w (`pose_weight`)."""
    return with_orientation(r, w * rotation_error(flange_rotations(q, g), rot))


def pose_jacobian(J, q, g: dict, w: float):
    """A pose's Jacobian [J; w J_ω] (B, 6, 6): the position's J (B, 3, 6) and the flange's angular
    Jacobian at q under geometry g, weighted by w (the rows of `pose_residual`)."""
    return torch.cat([J, w * angular_jacobian(q, g)], 1)


def jacobian(f, q):
    """Batched Jacobian J (B, 3, 6) = df/dq of a function f: (B, 6) -> (B, 3).

    Each output row depends only on its own input row (eval mode), so the
    gradient of the batch sum of output k gives every point's row k at once.
    """
    q = q.detach().requires_grad_(True)
    p = f(q)
    rows = [torch.autograd.grad(p[:, k].sum(), q, retain_graph=k < 2)[0] for k in range(3)]
    return torch.stack(rows, 1)


def slices(n: int, chunk: int) -> list:
    """0..n in ceil(n / chunk) near-equal consecutive slices (one when n <= chunk). Never a slice of a few
    rows beside big ones: the model's float32 layers give a batch of 1-3 rows other last bits, so a row's
    numbers would depend on where the cut fell."""
    k = max(1, -(-n // chunk))
    cuts = [n * i // k for i in range(k + 1)]
    return [slice(cuts[i], cuts[i + 1]) for i in range(k)]


def progress(solver: str, it: int, left: int, n: int, t0: float) -> None:
    log.info("%s: iteration %d, %d of %d points still solving (%.0f s)", solver, it, left, n, time.perf_counter() - t0)


def solve_adam(model, q0, target, cfg: dict, limits=None, chunk: int | None = None, history: bool = True):
    """The paper's procedure (sec. 2.3): cfg lr, max_iter, tol_mse (the `compensate:` section), the model
    evaluated `chunk` points at a time (`slices`; None: all at once), each step projected onto the joint
    limits (6, 2) rad (None: none). Returns q, prediction, iterations, converged, history (None when not asked
    for)."""
    lr, max_iter, tol_mse = cfg["lr"], cfg["max_iter"], cfg["tol_mse"]
    w = pose_weight(cfg) if target.shape[1] > 3 else None
    n = len(q0)
    parts = slices(n, chunk or max(n, 1))
    q = q0.clone().requires_grad_(True)
    opt = torch.optim.Adam([q], lr=lr)
    q_final, iters = q0.clone(), torch.full((n,), max_iter)
    done = torch.zeros(n, dtype=torch.bool)
    hist, t0 = [], time.perf_counter()
    for it in range(max_iter + 1):
        opt.zero_grad()
        rs, ms = [], []
        for s in parts:                                     # each part's graph freed after its backward
            r = residual(model, q[s], target[s], w)
            mse = (r ** 2).mean(1)                          # (B,) per-point MSE, mm² (a pose's: weighted, 6)
            if it < max_iter:
                mse.sum().backward()                        # rows apart: each its own gradient
            rs.append(r.detach())
            ms.append(mse.detach())
        r, mse = (torch.cat(x) if len(x) > 1 else x[0] for x in (rs, ms))
        if history:                                         # |pred - target| mm, a point's held from its stop
            e = position_error(r)
            hist.append(e if not hist else torch.where(done, hist[-1], e))
        new = (mse < tol_mse) & ~done
        q_final[new], iters[new] = q.detach()[new], it
        done |= new
        if done.all() or it == max_iter:
            break
        opt.step()
        if limits is not None:
            with torch.no_grad():
                q.clamp_(limits[:, 0], limits[:, 1])        # a step past a limit ends at it, as lm's
        if len(parts) > 1 and it % 50 == 0:
            progress("adam", it, int((~done).sum()), n, t0)
    q_final[~done] = q.detach()[~done]
    with torch.no_grad():
        pred = torch.cat([predict(model, q_final[s]) for s in parts])
    return q_final, pred, iters, done, torch.stack(hist) if history else None


LAM0 = 1e-3                                                 # lm's starting damping
LAM_MAX = 1e10          # lm's largest: a step 1e-10 of the undamped one finds nothing more, and λ·10 on
                        # every failed step would reach inf after ~310 (then NaN joints)


def lm_jacobian(model, jacobian_of: str, w: float | None = None):
    """The Jacobian lm steps with, q (A, 6) -> (A, 3, 6): "physics" takes the model's DH branch's
    geometric Jacobian (kinematics.fk_jacobian: exact, float64, one FK pass), leaving out the network's
    small slope (each step is then a chord step, the residual always from the whole model); "model"
    differentiates the whole model by autograd. For pose targets (w given) -> (A, 6, 6): the flange's
    angular Jacobian, times w, below."""
    if jacobian_of == "physics":
        position = lambda q: fk_jacobian(q, model.physics.geometry())[1]
    elif jacobian_of == "model":
        position = lambda q: jacobian(lambda x: predict(model, x), q)
    else:
        raise ValueError(f"params.yaml compensate.jacobian_of: {jacobian_of!r}; use physics or model")
    if w is None:
        return position
    return lambda q: pose_jacobian(position(q), q, model.physics.geometry(), w)


def lm_step(model, jac, q, r, err, lam, target, limits=None, physics_steps: int = 1, w: float | None = None):
    """One lm iteration for points q (A, 6), residual r (A, 3|6) mm, |r| err (A,), damping lam (A,):
    the step is kept where it lowers |r| (then λ/3, else λ·10). Returns the new q, r, err, lam.
    physics_steps > 1 (jacobian_of physics): the trial point is the end of that many damped steps on the
    physics branch alone with the network's correction at q held (`physics_trial`), one model evaluation
    still judging it. w: pose targets' weight (`residual`)."""
    if physics_steps > 1:
        q_try = physics_trial(model.physics.geometry(), q, r, lam, physics_steps, limits, target, w)
    else:
        q_try = clamped(q + min_norm_step(jac(q), r, lam), limits)   # (A, 6)
    with torch.no_grad():
        r_try = residual(model, q_try, target, w)
    err_try = r_try.norm(dim=1)
    ok = err_try < err
    q, err, lam = lm_keep(ok, q_try, err_try, q, err, lam)
    return q, torch.where(ok[:, None], r_try, r), err, lam


def clamped(q, limits):
    return q if limits is None else q.clamp(limits[:, 0], limits[:, 1])


def physics_trial(g, q, r, lam, steps: int, limits=None, target=None, w: float | None = None):
    """lm's trial point with the correction c = model(q) - physics(q) held: `steps` damped minimum-norm
    steps toward physics(q') = target - c = physics(q) - r on the physics branch (geometry g: exact
    position and Jacobian, one FK pass a step; the first step is the chord step). The network's evaluation,
    the costly part, then judges the end point once: about 2 model evaluations a point instead of 3 (the
    network's slope over a compensation's Δθ is ~1e-5 mm). q (A, 6), r (A, 3) -> (A, 6); a pose (r (A, 6),
    target (A, 12), w) steps on its orientation too, the physics branch's own."""
    rot = None if w is None else target_rotations(target)
    p, J, _ = physics_rows(q, g, rot, w)
    goal = p - r[:, :3]                                     # (A, 3) mm: where the physics branch must go
    q_try = clamped(q + min_norm_step(J, r, lam), limits)   # the chord step: r is the model's
    for _ in range(steps - 1):
        p, J, e = physics_rows(q_try, g, rot, w)
        q_try = clamped(q_try + min_norm_step(J, with_orientation(p - goal, e), lam), limits)
    return q_try


def lm_keep(ok, q_try, err_try, q, err, lam):
    """lm's rule, torch or numpy: where ok (the trial lowered |r|) the trial step is kept and λ/3, else
    the point stays and λ·10, at most LAM_MAX. Returns the new q, err, lam."""
    where = torch.where if isinstance(q, torch.Tensor) else np.where
    return where(ok[:, None], q_try, q), where(ok, err_try, err), where(ok, lam / 3, (lam * 10).clip(max=LAM_MAX))


def solve_lm(model, q0, target, cfg: dict, limits=None, lam0=LAM0, chunk: int | None = None,
             history: bool = True):
    """Batched Levenberg-Marquardt on the frozen model (`lm_step` until every point is within tol_mm):
    cfg max_iter, tol_mm, jacobian_of (`lm_jacobian`); each step on the points still solving, `chunk` at a
    time (`slices`; None: all at once). Returns q, prediction, iterations, converged, history (None when
    not asked for)."""
    max_iter, tol_mm = cfg["max_iter"], cfg["tol_mm"]
    w = pose_weight(cfg) if target.shape[1] > 3 else None
    jac = lm_jacobian(model, cfg["jacobian_of"], w)
    physics_steps = cfg.get("physics_steps", 1) if cfg["jacobian_of"] == "physics" else 1
    n = len(q0)
    chunk = chunk or max(n, 1)
    q = q0.clone()
    lam = torch.full((n,), lam0, dtype=DTYPE)
    iters = torch.full((n,), max_iter)
    done = torch.zeros(n, dtype=torch.bool)
    with torch.no_grad():
        r = torch.cat([residual(model, q[s], target[s], w) for s in slices(n, chunk)])   # (B, 3|6) mm
    err = r.norm(dim=1)
    hist, t0 = [position_error(r)] if history else None, time.perf_counter()
    for it in range(max_iter):
        new = (err < tol_mm) & ~done
        iters[new] = it
        done |= new
        if done.all():
            break
        active = (~done).nonzero().squeeze(1)               # active points
        if n > chunk:
            progress("lm", it, len(active), n, t0)
        for s in slices(len(active), chunk):
            a = active[s]
            q[a], r[a], err[a], lam[a] = lm_step(model, jac, q[a], r[a], err[a], lam[a], target[a], limits,
                                                   physics_steps, w)
        if history:
            hist.append(position_error(r))
    else:
        new = (err < tol_mm) & ~done
        iters[new] = max_iter
        done |= new
    return q, r[:, :3] + target[:, :3], iters, done, torch.stack(hist) if history else None


SOLVERS = {"adam": solve_adam, "lm": solve_lm}
CHUNK = 4096                        # points the model evaluates at once (compensate): bounds the memory


def in_blocks(solver, model, q0, tgt, cfg, limits, chunk: int, history: bool):
    """solver on the points in blocks of at most `chunk` (`slices`), each solved on its own (its numbers
    are those of its points alone, whatever runs beside it), as many at once as the cores hold at the
    caller's torch threads (one thread each: every core; the program command runs so). Returns what a
    solver returns; the history of a block that finished early is held at its last row."""
    blocks = slices(len(q0), chunk)
    if len(blocks) == 1:
        return solver(model, q0, tgt, cfg, limits, chunk=chunk, history=history)
    t0, done = time.perf_counter(), []

    def one(s):
        out = solver(model, q0[s], tgt[s], cfg, limits, chunk=chunk, history=history)
        done.append(s)
        log.info("compensate: %d of %d points solved (%.0f s)", sum(b.stop - b.start for b in done), len(q0),
                 time.perf_counter() - t0)
        return out

    workers = min(len(blocks), len(os.sched_getaffinity(0)) // torch.get_num_threads())
    with ThreadPoolExecutor(max(1, workers)) as pool:
        parts = list(pool.map(one, blocks))
    q, pred, iters, ok = (torch.cat([p[i] for p in parts]) for i in range(4))
    if not history:
        return q, pred, iters, ok, None
    rows = max(len(p[4]) for p in parts)                    # (iterations + 1, block) each, padded
    hist = torch.cat([torch.cat([p[4], p[4][-1:].expand(rows - len(p[4]), -1)]) for p in parts], dim=1)
    return q, pred, iters, ok, hist


def compensate(model, q0_deg: np.ndarray, target: np.ndarray, cfg: dict, robot=None, solver=None,
               chunk: int = CHUNK, history: bool = True):
    """Solve for every point, in blocks of `chunk` points on every core (`in_blocks`: bounded memory, a
    log line per block); returns (q_deg (n, 6), pred (n, 3), iterations, converged,
    history (iterations + 1, n): each point's |pred - target| mm, held from its stop; or None when not asked
    for, seconds)."""
    solver = solver or cfg["solver"]
    if solver not in SOLVERS:
        raise ValueError(f"params.yaml compensate.solver: unknown {solver!r}; use one of {sorted(SOLVERS)}")
    for p in model.parameters():
        p.requires_grad_(False)                             # Step 1: freeze
    model.eval()
    limits = None if robot is None else torch.as_tensor(np.radians(robot.limits_deg), dtype=DTYPE)
    q0 = torch.as_tensor(np.radians(q0_deg), dtype=DTYPE)
    tgt = torch.tensor(target, dtype=DTYPE)                 # a copy: the table's arrays may be read-only
    t0 = time.perf_counter()
    q, pred, iters, ok, hist = in_blocks(SOLVERS[solver], model, q0, tgt, cfg, limits, chunk, history)
    seconds = time.perf_counter() - t0
    return (np.degrees(q.numpy()), pred.numpy(), iters.numpy(), ok.numpy(), None if hist is None else hist.numpy(),
            seconds)

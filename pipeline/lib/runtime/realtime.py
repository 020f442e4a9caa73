"""The controller path: compensate one pose inside a 500 Hz cycle (2 ms).

The batched `lm` (solvers.py) iterates until every point is verified
within tol_mm; alone, one pose costs it about three model evaluations and
two Jacobians (5.6 ms here). A controller needs a fixed budget instead, so a
call here costs exactly two evaluations of the frozen model:

    r0 = p(q0) - target,  J0 = ∂p_theory/∂q (q0)     evaluation 1
    q1 = q0 - J0ᵀ (J0 J0ᵀ + μI)⁻¹ r0                 chord step: minimum-norm Δθ,
                                                     the network's small slope left out
    r1 = p(q1) - target,  J1 = ∂p_theory/∂q (q1)     evaluation 2
    |r1| < tol: return q1                            verified
    else:       return q2 = q1 - J1ᵀ (J1 J1ᵀ + μI)⁻¹ r1
                with the predicted residual |r1|²/|r0| (the chord step's contraction)

p is the whole model (DH branch + network, eq. 9); J is the DH branch's
geometric Jacobian (solvers.physics_rows; for a pose target with the flange's
orientation rows), one FK pass. Joint limits clamp
every step. `compile=True` runs both steps as one torch.compile graph: 10-20
s once, in the constructor, then a call costs about half of eager
PyTorch's (at batch 1, eager time goes as much to per-operator overhead as
to the matrix products). `batch` takes B poses in one evaluation (the
service, service.py, batches concurrent requests so), compiled for B = 1
only. `python -m pipeline.commands.bench speed` times it;
tests/test_compensate.py checks every answer against the model.

`two_steps` is the whole solve as one function of tensors: onnx_model.export_controller exports it as one
ONNX graph (models/controller.onnx), which onnx_model.OnnxRealtime runs on onnxruntime with the same call
and Results (`answers`), to 1e-9 rad (tests/test_export.py).
"""
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.lib.robot.kinematics import DTYPE
from pipeline.lib.runtime.solvers import cos_angle, min_norm_step, physics_rows, with_orientation

DAMPING = 1e-9                                             # μ of the controller's chord steps (tiny, fixed)


@dataclass
class Result:
    q: np.ndarray          # (6,) rad, the compensated joint angles
    residual_mm: float     # |p(q) - target|: measured when verified, else predicted
    verified: bool         # residual_mm was measured by the second evaluation
    converged: bool        # residual_mm < tol_mm
    in_workspace: bool | None = None   # q within the trained workspace (None: no workspace given)


class Realtime:
    """Compensate single poses with a frozen BoTER: `Realtime(model)(q0_rad, target_mm) -> Result`."""

    def __init__(self, model, limits_rad: np.ndarray | None = None, tol_mm: float = 1e-3,
                 damping: float = DAMPING, compile: bool = False, workspace=None):
        model.eval()
        for p in model.parameters():
            p.requires_grad_(False)
        self.model, self.tol = model, tol_mm
        self.limits = np.array([[-np.inf, np.inf]] * 6) if limits_rad is None else np.asarray(limits_rad, float)
        self.lo, self.hi = (torch.as_tensor(self.limits[:, i], dtype=DTYPE) for i in (0, 1))
        self.damping, self.workspace = damping, workspace   # workspace: lib/workspace.Workspace
        self.solve = self._solve                            # a single pose's (batches run eager: inductor
        if compile:                                         # fails on the batched transformer fast path)
            self.solve = torch.compile(self._solve, dynamic=False)
            self(np.zeros(6), np.zeros(3))                  # compile now, not in the first cycle

    def _solve(self, q0, target):
        """Both steps (one graph when compiled): q1, q2 (B, 6) and |r0|, |r1| (B,)."""
        return two_steps(self.model, q0, target, self.lo, self.hi, self.damping)

    def __call__(self, q0_rad, target_mm) -> Result:
        return self.batch(np.reshape(q0_rad, (1, 6)), np.reshape(target_mm, (1, 3)))[0]

    @torch.inference_mode()
    def batch(self, q0_rad, target_mm) -> list[Result]:
        """Compensate B poses at once, (B, 6) rad and (B, 3) mm: each as a call alone would (the same
        steps, one evaluation of the model for all)."""
        # fresh contiguous copies: the compiled graph is specialised to one layout (no recompiles)
        q0 = torch.tensor(np.asarray(q0_rad, float).reshape(-1, 6), dtype=DTYPE)
        target = torch.tensor(np.asarray(target_mm, float).reshape(-1, 3), dtype=DTYPE)
        q1, q2, r0, r1 = (t.numpy() for t in (self.solve if len(q0) == 1 else self._solve)(q0, target))
        return answers(q1, q2, r0, r1, self.tol, self.workspace, self.limits)


def two_steps(model, q0, target, lo, hi, damping, tcp_mm=None, rot=None, w=None):
    """The two chord steps from q0 (B, 6) rad towards target (B, 3) mm, joint limits lo, hi (6,) rad,
    damping μ (a float or (B,)): q1, q2 (B, 6) and |r0|, |r1| (B,) mm. What Realtime runs (eager or compiled) and what
    onnx_model.export_controller exports as one graph. tcp_mm (3,), flange frame: the target is that point's
    (the physics branch with it as its tool, the network's correction unchanged: lib/robot/tcp.py AtTcp). rot
    (B, 3, 3) and w (mm/rad): a pose, the flange's orientation too (six equations, solvers.residual's
    weighting; |r| then the weighted norm)."""
    q1, r0 = chord_step(model, q0, target, lo, hi, damping, tcp_mm, rot, w)
    q2, r1 = chord_step(model, q1, target, lo, hi, damping, tcp_mm, rot, w)
    return q1, q2, r0, r1


def chord_step(model, q, target, lo, hi, damping, tcp_mm=None, rot=None, w=None):
    """One chord step from q (B, 6): returns (the next q (B, 6), |residual at q| (B,) mm). For a pose the step
    drives [r, w e] (e: sin θ times the axis) to zero, and within 90° of rot the |residual| returned is |[r, w e]|;
    beyond (cos θ < 0), the orientation's part is w (2 - sin θ), ≥ w, growing to 2w at θ = 180°, where w sin θ
    is zero again and a flange turned half round would read as reached (`answers`). (Not atan2: onnxruntime
    has no float64 Atan.)"""
    g = model.physics.geometry()
    g = g if tcp_mm is None else {**g, "tool": tcp_mm}
    if rot is None:
        p, J, e = physics_rows(q, g)                      # (B, 3), (B, 3, 6), None
    else:                                                 # (B, 3), (B, 6, 6), (B, 3), and the flange's R for θ
        p, J, e, R = physics_rows(q, g, rot, w, flange=True)
    r = with_orientation(p + model.delta(q) - target, e)  # (B, 3), eq. 9; a pose's (B, 6): the orientation below
    q_next = q + min_norm_step(J, r, damping)
    if rot is None:
        return torch.clamp(q_next, lo, hi), r.norm(dim=1)
    cos = cos_angle(R, rot)                                                           # (B,) cos θ
    beyond = torch.sqrt((r[:, :3] ** 2).sum(1) + (2 * w - e.norm(dim=1)) ** 2)          # w (2 - sin θ)
    return torch.clamp(q_next, lo, hi), torch.where(cos >= 0, r.norm(dim=1), beyond)


def answers(q1, q2, r0, r1, tol_mm: float, workspace=None, limits=None) -> list[Result]:
    """The two steps' outputs (numpy: (B, 6), (B, 6), (B,), (B,)) as B Results: q1 when |r1| < tol_mm
    (verified), else q2 with the predicted residual |r1|²/|r0|, converged only below tol_mm and with no joint
    of q2 on one of the joint limits (6, 2) rad (clamped there: the prediction assumed the step whole);
    in_workspace when a workspace is given."""
    lo, hi = (np.full(6, -np.inf), np.full(6, np.inf)) if limits is None else np.asarray(limits, float).T
    out = []
    for i in range(len(q1)):
        a, b = float(r0[i]), float(r1[i])
        if b < tol_mm:
            out.append(Result(q1[i], b, True, True))
        else:
            predicted = b * b / a if b < a else float("inf")
            clamped = bool(((q2[i] <= lo) | (q2[i] >= hi)).any())
            out.append(Result(q2[i], predicted, False, predicted < tol_mm and not clamped))
    if workspace is not None and out:
        inside = workspace(np.degrees([r.q for r in out]))[1]
        for r, w in zip(out, inside):
            r.in_workspace = bool(w)
    return out


def check(rt, q0_rad: np.ndarray, targets: np.ndarray, model=None) -> dict:
    """Compensate every (q0, target) pair (n, 6), (n, 3) one call at a time with rt (a Realtime or
    onnx_model.OnnxRealtime); how the answers did, their residuals measured by an independent batched
    evaluation of the PyTorch model (default: rt's)."""
    results = [rt(a, b) for a, b in zip(q0_rad, targets)]
    with torch.no_grad():
        pred = (rt.model if model is None else model)(torch.as_tensor(np.array([r.q for r in results]), dtype=DTYPE))[0].numpy()
    true = np.linalg.norm(pred - targets, axis=1)
    return {"n_points": len(results), "evaluations_per_call": 2,
            "verified_share": float(np.mean([r.verified for r in results])),
            "converged_share": float(np.mean([r.converged for r in results])),
            "true_residual_mm_max": float(true.max()),
            # the answers returned on a prediction: what was predicted, what they measure
            "predicted_residual_mm_max": max([r.residual_mm for r in results if not r.verified], default=0.0),
            "unverified_true_residual_mm_max": float(max([t for r, t in zip(results, true) if not r.verified],
                                                         default=0.0)),
            "outside_workspace": (None if rt.workspace is None
                                  else int(sum(not r.in_workspace for r in results)))}

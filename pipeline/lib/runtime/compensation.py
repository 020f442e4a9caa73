"""The Δθ table (docs/data-format.md, reports/compensation.csv): built here, and only here, for the
compensate stage, `compensate --targets` and the program compensator."""
from dataclasses import dataclass

import numpy as np
import pandas as pd
import torch

from pipeline.lib.project.columns import COMPENSATION, DJ_DEG, JCOMP_DEG, JOINTS_DEG, PRED, TARGET
from pipeline.lib.robot.kinematics import DTYPE, TOOL_ROT, flange_rotations
from pipeline.lib.runtime.solvers import compensate, orientation_angle


@dataclass
class Solved:
    """What a solver returned for n targets (solvers.compensate)."""
    q_deg: np.ndarray        # (n, 6) the compensated joints
    pred: np.ndarray         # (n, 3) mm, the model at them
    iterations: np.ndarray   # (n,)
    converged: np.ndarray    # (n,) bool
    history: np.ndarray | None   # (iterations + 1, n) residual mm; None when not asked for
    seconds: float
    orientation_arcsec: np.ndarray | None = None   # (n,) the flange's orientation off its target; None: no target


def solve(model, q0_deg: np.ndarray, target: np.ndarray, cfg: dict, robot, solver: str | None = None,
          history: bool = True, flange_rot: np.ndarray | None = None) -> Solved:
    """Compensate every (q0, target) with `solver` (default cfg["solver"]) within the robot's limits (the
    model evaluated solvers.CHUNK points at a time: one batch's numbers, bounded memory); with flange_rot
    (n, 3, 3), the flange's orientation is a target too (six equations, lib/runtime/solvers.py). `converged`:
    reached, within cfg tol_mm (and tol_arcsec of the whole angle) and the joint limits, whatever the solver's
    own stop rule."""
    if flange_rot is None:
        s = Solved(*compensate(model, q0_deg, target, cfg, robot, solver, history=history))
    else:
        pose = np.hstack([target, flange_rot.reshape(len(target), 9)])    # (n, 12)
        s = Solved(*compensate(model, q0_deg, pose, cfg, robot, solver, history=history))
        angle = orientation_angle(model.physics.geometry(), torch.as_tensor(np.radians(s.q_deg), dtype=DTYPE),
                                  torch.as_tensor(pose, dtype=DTYPE))
        s.orientation_arcsec = np.degrees(angle.numpy()) * 3600   # the whole angle: 648000 for a flange turned half round
        s.converged &= s.orientation_arcsec <= cfg["tol_arcsec"]  # the solvers' |e| is sin θ: small again near 180°
    s.converged &= np.linalg.norm(s.pred - target, axis=1) <= cfg["tol_mm"]    # reached, whatever the solver's stop
    if robot is not None:                                                      # (adam's: the paper's MSE)
        s.converged &= ~robot.check_joints(s.q_deg).any(1)
    return s


def nominal_flange(q0_deg: np.ndarray, nominal: dict) -> np.ndarray:
    """The flange's orientation (n, 3, 3), base frame, of joints q0 (n, 6) deg under the nominal geometry:
    an offline-programmed waypoint's orientation target."""
    return flange_rotations(torch.as_tensor(np.radians(q0_deg), dtype=DTYPE), nominal).numpy()


def orientation_targets(model, cfg: dict) -> bool:
    """Whether offline-programmed targets carry their nominal orientation (`compensate.orientation`): only
    for a model calibrated with the probe's orientation (its geometry has a tool rotation); a
    position-only model's orientation was never measured."""
    return bool(cfg.get("orientation", False)) and TOOL_ROT in model.physics.geometry()


def delta_table(point_id, q0_deg: np.ndarray, target: np.ndarray, solved: Solved, workspace) -> pd.DataFrame:
    """The Δθ table (columns COMPENSATION): Δθ = θ_final - θ_initial (eq. 19, degrees), the model's
    prediction and residual, and `uncertainty_mm` / `in_workspace` at the compensated joints."""
    table = pd.DataFrame({"point_id": list(point_id)})
    table[JOINTS_DEG] = q0_deg
    table[DJ_DEG] = solved.q_deg - q0_deg
    table[JCOMP_DEG] = solved.q_deg
    table[TARGET], table[PRED] = target, solved.pred
    table["residual_mm"] = np.linalg.norm(solved.pred - target, axis=1)
    table["iterations"], table["converged"] = solved.iterations, solved.converged
    table["uncertainty_mm"], table["in_workspace"] = workspace(solved.q_deg)
    table["orientation_residual_arcsec"] = np.nan if solved.orientation_arcsec is None else solved.orientation_arcsec
    return table[COMPENSATION]


def reach_mm(g: dict) -> float:
    """A generous reach bound (mm) of geometry g: |a| + |d| of every link, the tool and the base shift. A
    target farther from the base can be reached by no joint angles."""
    return float(g["a"].abs().sum() + g["d"].abs().sum() + g["tool"].norm() + g["base"][3:].norm())

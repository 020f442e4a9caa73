"""The Δθ table (docs/data-format.md, reports/compensation.csv): built here, and only here, for the
compensate stage, `compensate --targets` and the program compensator."""
from dataclasses import dataclass

import numpy as np
import pandas as pd

from .columns import COMPENSATION, DJ_DEG, JCOMP_DEG, JOINTS_DEG, PRED, TARGET
from .solvers import compensate


@dataclass
class Solved:
    """What a solver returned for n targets (solvers.compensate)."""
    q_deg: np.ndarray        # (n, 6) the compensated joints
    pred: np.ndarray         # (n, 3) mm, the model at them
    iterations: np.ndarray   # (n,)
    converged: np.ndarray    # (n,) bool
    history: np.ndarray | None   # (iterations + 1, n) residual mm; None when not asked for
    seconds: float


def solve(model, q0_deg: np.ndarray, target: np.ndarray, cfg: dict, robot, solver: str | None = None,
          history: bool = True) -> Solved:
    """Compensate every (q0, target) with `solver` (default cfg["solver"]) within the robot's limits (the
    model evaluated solvers.CHUNK points at a time: one batch's numbers, bounded memory)."""
    return Solved(*compensate(model, q0_deg, target, cfg, robot, solver, history=history))


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
    return table[COMPENSATION]


def reach_mm(g: dict) -> float:
    """A generous reach bound (mm) of geometry g: |a| + |d| of every link, the tool and the base shift. A
    target farther from the base can be reached by no joint angles."""
    return float(g["a"].abs().sum() + g["d"].abs().sum() + g["tool"].norm() + g["base"][3:].norm())

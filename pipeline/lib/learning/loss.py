"""SPI loss (sec. 2.2): data residual + spatial-physics residual, weighted.

L_data    = mean_b ||p_pred - p_gt||^2                                (eq. 10)
D[i, j]   = ||Y_i - Y_j||^2, for theory and prediction               (eqs. 11-13)
L_physics = MSE(D_theory / max D_theory, D_pred / max D_pred)         (eqs. 14-16)

Weightings (`loss.weighting`):
  paper        L = exp(l_d) L_data + exp(l_p) L_physics, l = log λ trainable (eqs. 17-18)
  uncertainty  L = Σ_k exp(-s_k) L_k + s_k, s_k trainable (homoscedastic uncertainty)
  fixed        L = λ_d L_data + λ_p L_physics
"""
import math

import torch
from torch import nn

from pipeline.lib.project.config import WEIGHTINGS    # declared with the settings' rules


def data_loss(p_pred, p_gt):                               # (B, 3), (B, 3) -> ()
    return ((p_pred - p_gt) ** 2).sum(-1).mean()


def sq_distance_matrix(Y):                                 # (B, 3) -> (B, B)
    return ((Y.unsqueeze(0) - Y.unsqueeze(1)) ** 2).sum(-1)


def physics_loss(p_pred, p_theory):                        # (B, 3), (B, 3) -> ()
    Dt, Dp = sq_distance_matrix(p_theory), sq_distance_matrix(p_pred)
    return ((Dt / Dt.max() - Dp / Dp.max()) ** 2).mean()


class SPILoss(nn.Module):
    def __init__(self, weighting="uncertainty", physics=True, lambda_data=1.0, lambda_physics=1.0):
        super().__init__()
        if weighting not in WEIGHTINGS:
            raise ValueError(f"params.yaml loss.weighting: unknown {weighting!r}; use one of {WEIGHTINGS}")
        self.weighting, self.use_physics = weighting, physics
        lam = torch.tensor([lambda_data, lambda_physics], dtype=torch.float64)
        if weighting == "paper":
            self.log_lambda = nn.Parameter(lam.log())           # eq. 17: λ = exp(log λ)
        elif weighting == "uncertainty":
            self.s = nn.Parameter(-lam.log())                   # starts at the same weights
        else:
            self.register_buffer("lam", lam)

    def weights(self) -> torch.Tensor:
        """Current effective weights (λ_data, λ_physics)."""
        if self.weighting == "paper":
            return self.log_lambda.exp()
        if self.weighting == "uncertainty":
            return torch.exp(-self.s)
        return self.lam

    def terms(self, p_pred, p_gt, p_theory):
        """(total, {"data": L_data, "physics": L_physics}) with the terms as tensors (NaN without the
        physics term): no host sync, so a captured CUDA graph can hold it (training.EpochGraph)."""
        terms = [data_loss(p_pred, p_gt)]
        if self.use_physics:
            terms.append(physics_loss(p_pred, p_theory))
        L = torch.stack(terms)
        w = self.weights()[: len(terms)]
        total = (w * L).sum()                                   # eq. 18
        if self.weighting == "uncertainty":
            total = total + self.s[: len(terms)].sum()
        return total, {"data": L[0], "physics": L[1] if self.use_physics else math.nan}

    def forward(self, p_pred, p_gt, p_theory):
        """Returns (total, {"data": .., "physics": ..}) for logging, the terms as floats."""
        total, parts = self.terms(p_pred, p_gt, p_theory)
        return total, {k: v.item() if isinstance(v, torch.Tensor) else v for k, v in parts.items()}

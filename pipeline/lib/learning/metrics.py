"""Error metrics of sec. 4.1: MAE/MSE/RMSE per axis and 3D (eqs. 27-38), R² on error vectors (eqs. 39-42)."""
import numpy as np
import pandas as pd

from pipeline.lib.project.columns import AXES, MEAS, SPLITS, THEORY


def r2(ss_res: float, ss_tot: float) -> float | None:
    """1 - ss_res / ss_tot (eqs. 39-42); None where ss_tot is 0 (nothing to explain: R² is undefined)."""
    return float(1 - ss_res / ss_tot) if ss_tot > 0 else None


def seed_std(values) -> float | None:
    """The spread the project quotes as "mean ± std" over training seeds: the population standard deviation
    (ddof 0, docs/results.md); None for fewer than two seeds (one run has no spread to tell)."""
    return float(np.std(values)) if len(values) > 1 else None


def regression_metrics(pred: np.ndarray, real: np.ndarray, theory: np.ndarray) -> dict:
    """pred, real, theory: (n, 3) mm -> {"x"|"y"|"z"|"3d": {"mae", "mse", "rmse", "r2"}}.

    R² compares the predicted error Δ̂ = pred - theory with the real error
    Δ = real - theory, the denominator taken around the mean real Δ (docs/method.md). Where the real
    errors do not vary (a split of one point) R² is undefined: None (JSON null), never ±inf or NaN.
    """
    e = pred - real                                        # (n, 3) prediction error
    d_real = real - theory                                 # (n, 3) real error vectors
    ss_tot = ((d_real - d_real.mean(0)) ** 2)              # (n, 3)
    out = {}
    for k, ax in enumerate(AXES):
        mse = float(np.mean(e[:, k] ** 2))
        out[ax] = {"mae": float(np.mean(np.abs(e[:, k]))), "mse": mse, "rmse": float(np.sqrt(mse)),
                   "r2": r2(np.sum(e[:, k] ** 2), ss_tot[:, k].sum())}
    mse3 = float(np.mean((e ** 2).sum(1)))                 # eq. 34
    out["3d"] = {"mae": float(np.mean(np.linalg.norm(e, axis=1))),   # eq. 30
                 "mse": mse3, "rmse": float(np.sqrt(mse3)),          # eq. 38
                 "r2": r2((e ** 2).sum(), ss_tot.sum())}               # eq. 42
    return out


def drive_table(achieved: np.ndarray, target: np.ndarray, tol_mm: float = 0.5) -> dict:
    """The paper's Table 9 layout for a drive check (mm): per axis the mean, max and min of |error| and the
    signed error's std; the 3D error's; and the share of points within ±tol on every axis."""
    e = achieved - target
    out = {ax: {"mean": float(np.abs(e[:, k]).mean()), "std": float(e[:, k].std()),
                "max": float(np.abs(e[:, k]).max()), "min": float(np.abs(e[:, k]).min())}
           for k, ax in enumerate(AXES)}
    n3 = np.linalg.norm(e, axis=1)
    out["3d"] = {"mean": float(n3.mean()), "std": float(n3.std()), "max": float(n3.max()),
                 "min": float(n3.min())}
    out["n"] = len(e)
    out["within_tol_share"] = float((np.abs(e) <= tol_mm).all(1).mean())
    out["tol_mm"] = tol_mm
    return out


def split_metrics(df: pd.DataFrame, pred: np.ndarray) -> dict:
    """{split: regression_metrics} of predictions `pred` (rows aligned with df: split, meas, theory)."""
    return {s: regression_metrics(pred[m], df.loc[m, MEAS].to_numpy(), df.loc[m, THEORY].to_numpy())
            for s in SPLITS if (m := (df.split == s).to_numpy()).any()}


def stats(e: np.ndarray) -> dict:
    """n, mean, p95 (numpy's linear percentile) and max of 3D errors e (mm); None where there are none."""
    e = np.asarray(e, float)
    if not len(e):
        return {"n": 0, "mean": None, "p95": None, "max": None}
    return {"n": int(len(e)), "mean": float(e.mean()), "p95": float(np.percentile(e, 95)), "max": float(e.max())}

"""Judging a calibration on an independent campaign (docs/data-format.md, "Validation").

Every method predicts the marker in the robot's base frame; the campaign
measured it in its tracker's frame. Two ways to compare them:

    same    the tracker did not move: map the measurements with the training campaign's
            frame (reports/frame.json); every point is judged.
    refit   the tracker moved (or may have): each method gets its own rigid frame, fitted
            by robust Kabsch (eqs. 20-26, misreads rejected) on the same registration
            points, and is judged on the others. Registration rule: `register_points`
            points spread over the measured cloud by farthest-point sampling (from the
            point nearest the centroid), so the frame is well conditioned and most of the
            campaign is left to judge. Only the frame is refitted, not the tool: the
            model predicts positions, not flange poses, so the three methods are
            registered alike. The nominal method's registration is checked like the
            frame stage's fit (frames.check_fit): a mirrored or far-off campaign stops.

ISO 9283 position accuracy where the campaign commands one position several
times (a `commanded` column group): per commanded position, with the
deviations d_i = x_i - c_i of the attained marker positions from where the
command put the marker (its orientation may differ between visits),
AP_P = |mean d_i| and the spread RP = mean |d_i - mean d|, both from the
measurements and from each method's predictions, and bar_error =
|predicted mean - measured mean|: how well the method knows where the robot
really goes for that command.
"""
import numpy as np
import pandas as pd

from .frames import check_fit, robust_kabsch, to_base

METHODS = ("nominal", "calibrated", "model")


def registration_subset(P: np.ndarray, n: int) -> np.ndarray:
    """Bool mask of n points of P (m, 3) spread by farthest-point sampling (deterministic)."""
    n = min(n, len(P))
    chosen = [int(np.argmin(np.linalg.norm(P - P.mean(0), axis=1)))]
    d = np.linalg.norm(P - P[chosen[0]], axis=1)
    for _ in range(n - 1):
        chosen.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(P - P[chosen[-1]], axis=1))
    mask = np.zeros(len(P), bool)
    mask[chosen] = True
    return mask


def judge(pred: dict, P_world: np.ndarray, mode: str, frame: dict, n_register: int, frame_cfg: dict):
    """Each method's 3D error per point and the frame it was judged in.

    pred: {method: (m, 3) base frame}; P_world: (m, 3) tracker frame. Returns
    (errors {method: (m,)}, registered (m,) bool, frames {method: {"R", "t"}}); registered
    points are not judged (their errors are the registration residuals).
    """
    if mode == "same":
        P = to_base(P_world, frame)
        return ({m: np.linalg.norm(p - P, axis=1) for m, p in pred.items()}, np.zeros(len(P), bool),
                {m: {"R": np.asarray(frame["R"]), "t": np.asarray(frame["t"])} for m in pred})
    if mode != "refit":
        raise ValueError(f"params.yaml validate.campaigns.*.frame: {mode!r}; use same or refit")
    reg = registration_subset(P_world, n_register)
    errors, frames = {}, {}
    for m, p in pred.items():
        R, t, inl, _ = robust_kabsch(p[reg], P_world[reg], frame_cfg["outlier_k"], frame_cfg["outlier_min_mm"])
        if m == "nominal":
            check_fit(p[reg][inl], P_world[reg][inl], R, t, "the refit registration (nominal)", frame_cfg)
        errors[m] = np.linalg.norm(p @ R.T + t - P_world, axis=1)
        frames[m] = {"R": R, "t": t}
    return errors, reg, frames


def stats(e: np.ndarray) -> dict:
    if not len(e):
        return {"n": 0, "mean": None, "p95": None, "max": None}
    return {"n": int(len(e)), "mean": float(e.mean()), "p95": float(np.percentile(e, 95)), "max": float(e.max())}


def summary(table: pd.DataFrame, mode: str) -> dict:
    """validation.json's entry for one campaign (docs/data-format.md keys, then the in/out split)."""
    j = table[~table.registered]
    s = {m: stats(j[f"error_{m}_mm"].to_numpy()) for m in METHODS}
    inside = j.in_workspace.to_numpy()
    return {
        "n": len(table), "n_judged": len(j), "frame": mode, "n_register": int(table.registered.sum()),
        "mean_3d_mm": {m: s[m]["mean"] for m in METHODS},
        "p95_3d_mm": {m: s[m]["p95"] for m in METHODS},
        "max_3d_mm": {m: s[m]["max"] for m in METHODS},
        "in_workspace_share": float(inside.mean()) if len(j) else None,
        "uncertainty_mm_mean": float(j.uncertainty_mm.mean()) if len(j) else None,
        "by_workspace": {w: {m: stats(j.loc[inside == (w == "in"), f"error_{m}_mm"].to_numpy())
                             for m in METHODS} for w in ("in", "out")},
        "uncertainty_coverage": {w: (float((k.error_model_mm <= k.uncertainty_mm).mean()) if len(k) else None)
                                 for w, k in (("all", j), ("in", j[inside]), ("out", j[~inside]))},
    }


def position_accuracy(commanded: np.ndarray, group: np.ndarray, measured: dict, pred: dict,
                      judged: np.ndarray) -> dict:
    """ISO 9283 AP_P and RP per method, measured and predicted, averaged over commanded positions.

    commanded (m, 3): each point's commanded marker position (base frame, mm); group (m, k): what
    was commanded (points with equal rows reached the same commanded position, maybe in another
    joint configuration and orientation); measured {method: (m, 3) in that method's base frame};
    pred {method: (m, 3)}. Per position, with deviations d_i = x_i - c_i: AP_P = |mean d_i|,
    RP = mean |d_i - mean d|, bar_error = |mean(pred) - mean(measured)|. Judged points only,
    positions reached at least twice.
    """
    _, g = np.unique(np.round(group[judged], 6), axis=0, return_inverse=True)
    g = g.ravel()
    c = commanded[judged]
    out = {}
    for m in pred:
        rows = {"ap_measured": [], "ap_predicted": [], "rp_measured": [], "rp_predicted": [], "bar_error": []}
        for k in np.unique(g):
            idx = np.flatnonzero(g == k)
            if len(idx) < 2:
                continue
            bars = {}
            for kind, x in (("measured", measured[m][judged][idx]), ("predicted", pred[m][judged][idx])):
                d = x - c[idx]
                bars[kind] = d.mean(0)
                rows[f"ap_{kind}"].append(np.linalg.norm(bars[kind]))
                rows[f"rp_{kind}"].append(np.linalg.norm(d - bars[kind], axis=1).mean())
            rows["bar_error"].append(np.linalg.norm(bars["predicted"] - bars["measured"]))
        out[m] = {"positions": len(rows["ap_measured"]),        # means over the commanded positions
                  **{f"{k}_mm": (float(np.mean(v)) if v else None) for k, v in rows.items()}}
    return out

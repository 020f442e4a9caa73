"""Per-joint error maps: the parts of the correction that extrapolate along the joints.

Transmission and encoder errors of a joint depend on that joint's angle alone; the deflection of
a joint on the gravity load it carries. Each is a smooth function of one number, so a new pose
whose every joint (or load) lies where that joint (or load) was measured is covered, however new
the combination: the joint-space network (model.py) covers only poses near a training pose.

    δθ_i = a_i(θ_i) + l_i(τ_i)                                    rad, added to joint i's angle

angle map a_i   periodic cubic B-spline in the joint's angle (360°: gear and encoder errors repeat
                every turn of the output), `amap_coef` (6, Na) rad on Na uniform knots; weighted by
                `amap_cover` (6, 360): 1 within `reach_deg` of an angle measured in training,
                falling to 0 over `fade_deg` (linear interpolation between 1° bins): where a joint
                was never measured its map says nothing.
load map l_i    cubic B-spline in the joint's gravity torque τ_i (N·m, kinematics.gravity_torques)
                on [lmap_lo_i, lmap_lo_i + n·lmap_step_i] (`lmap_coef` (6, n+3) rad), holding its edge
                value beyond and fading to 0 over a tenth of the range: the part of the joint's
                deflection the linear compliance does not explain (stiffness that changes with load).

Both enter the chain as joint-angle errors (kinematics.deflected), so they are physically joint
errors: the DH chain stays exact, Δθ compensation through it stays exact, and an angle map cannot
re-learn a link length. `fit` identifies them by penalised linear least squares on the residual
a calibration leaves, through the chain's Jacobian: a Gaussian prior of `prior_arcsec` on every
coefficient (no joint error is larger) and of `smooth_arcsec` on the second difference of
neighbouring coefficients (how fast it may change from knot to knot), residual noise `noise_mm`;
and none of what the calibration already holds (calibration_like: a joint offset, the linear
compliance), so a map cannot silently take over a calibration parameter.
"""
import numpy as np
import torch

MAP_KEYS = ("amap_coef", "amap_cover", "lmap_lo", "lmap_step", "lmap_coef")
ARCSEC = np.pi / (180 * 3600)


def cubic_weights(t):
    """The four uniform cubic B-spline values at fraction t in [0, 1): (..., 4); numpy or torch."""
    lib = torch if isinstance(t, torch.Tensor) else np
    t2, t3 = t * t, t * t * t
    return lib.stack([(1 - t) ** 3, 3 * t3 - 6 * t2 + 4, -3 * t3 + 3 * t2 + 3 * t + 1, t3], -1) / 6.0


# ----------------------------------------------------------------------------- evaluation (torch)

def angle_terms(q_deg: torch.Tensor, coef: torch.Tensor, cover: torch.Tensor):
    """Indices (B, 6, 4) into coef's columns, weights (B, 6, 4) incl. coverage, for angles q (B, 6) deg."""
    n = coef.shape[1]
    a = torch.remainder(q_deg, 360.0)                                     # (B, 6) in [0, 360)
    u = a * (n / 360.0)
    k = torch.floor(u)
    idx = torch.remainder(k.long().unsqueeze(-1) + torch.arange(4, device=k.device), n)    # (B, 6, 4)
    b = torch.floor(a)                                                    # coverage bins: 1 degree
    f = a - b
    rows = torch.arange(6, device=b.device).expand_as(b)
    w = (1 - f) * cover[rows, b.long() % 360] + f * cover[rows, (b.long() + 1) % 360]
    return idx, cubic_weights(u - k) * w.unsqueeze(-1)


def load_terms(tau: torch.Tensor, lo: torch.Tensor, step: torch.Tensor, n: int):
    """Indices (B, 6, 4) and weights (B, 6, 4) of the load maps at torques tau (B, 6) N·m (0 where step 0)."""
    on = step > 0
    safe = torch.where(on, step, torch.ones_like(step))
    hi = lo + safe * n
    x = torch.minimum(torch.maximum(tau, lo), hi)
    u = (x - lo) / safe
    k = torch.nan_to_num(torch.minimum(torch.floor(u), torch.full_like(u, n - 1)))   # a NaN torque: index 0, NaN out
    fade = (1.0 - torch.maximum(lo - tau, tau - hi).clamp(min=0) / (0.1 * safe * n)).clamp(0.0, 1.0)
    w = cubic_weights(u - k) * (fade * on).unsqueeze(-1)
    return k.long().unsqueeze(-1) + torch.arange(4, device=k.device), w


def joint_errors(q_rad: torch.Tensor, tau: torch.Tensor, g: dict) -> torch.Tensor:
    """δθ (B, 6) rad of geometry g's maps at joint angles q (B, 6) rad and gravity torques tau (B, 6)."""
    out = torch.zeros_like(q_rad)
    rows = torch.arange(6, device=q_rad.device)[:, None]                  # (6, 1): joint i's row of a (6, M) table
    if "amap_coef" in g:
        idx, w = angle_terms(torch.rad2deg(q_rad), g["amap_coef"], g["amap_cover"])
        out = out + (g["amap_coef"][rows, idx] * w).sum(-1)          # (B, 6, 4) -> (B, 6)
    if "lmap_coef" in g:
        idx, w = load_terms(tau, g["lmap_lo"], g["lmap_step"], g["lmap_coef"].shape[1] - 3)
        out = out + (g["lmap_coef"][rows, idx] * w).sum(-1)
    return out


# ----------------------------------------------------------------------------- coverage

def coverage(train_q_deg: np.ndarray, joints, reach_deg: float, fade_deg: float) -> np.ndarray:
    """(6, 360): per joint and degree of its (wrapped) angle, 1 within reach_deg of a training angle,
    falling linearly to 0 over fade_deg beyond; 0 for joints without a map."""
    grid = np.arange(360.0)
    out = np.zeros((6, 360))
    for i in joints:
        seen = np.unique(np.round(np.remainder(train_q_deg[:, i - 1], 360.0), 1))
        d = np.full(360, np.inf)
        for s in np.array_split(seen, max(1, len(seen) // 512)):
            d = np.minimum(d, np.abs((grid[:, None] - s[None] + 180.0) % 360.0 - 180.0).min(1))
        out[i - 1] = np.clip(1.0 - (d - reach_deg) / fade_deg, 0.0, 1.0)
    return out


def angle_covered(cover: np.ndarray, q_deg: np.ndarray) -> np.ndarray:
    """(n, 6) bool: joint j's angle of pose i lies in a 1° bin its map covers (cover (6, 360), the
    bins' coverage weights, `coverage`; bin = floor(q mod 360)). What the workspace guard, validate's
    per-joint shares and the planner all call covered."""
    b = np.floor(np.remainder(np.atleast_2d(q_deg), 360.0)).astype(int) % 360   # (n, 6)
    return np.asarray(cover)[np.arange(6), b] >= 1.0


def in_range(q_deg: np.ndarray, tau: np.ndarray, maps: dict) -> dict:
    """Per pose (n,) bool: every mapped joint's angle inside its coverage ("angle_map"), every mapped
    joint's torque inside its trained range ("load_map")."""
    out = {}
    if "amap_cover" in maps:
        cover = np.asarray(maps["amap_cover"])
        out["angle_map"] = angle_covered(cover, q_deg)[:, cover.any(1)].all(1)
    if "lmap_step" in maps:
        lo, step = np.asarray(maps["lmap_lo"]), np.asarray(maps["lmap_step"])
        n, on = np.asarray(maps["lmap_coef"]).shape[1] - 3, np.asarray(maps["lmap_step"]) > 0
        ok = (tau >= lo) & (tau <= lo + step * n)
        out["load_map"] = ok[:, on].all(1)
    return out


# ----------------------------------------------------------------------------- identification

def design(q_deg: np.ndarray, tau: np.ndarray, J: np.ndarray, maps: dict) -> tuple[np.ndarray, list]:
    """The linear model of the residual: X (3n, P) with r ≈ X c, c every map's coefficients (rad) in the
    order [angle maps of joints on, load maps of joints on], and the blocks [(part, joint, columns)].
    J (n, k, 6) mm/rad: the chain's Jacobian at the poses (k = 3 position rows, or 6 with the weighted
    orientation rows), X then (k·n, P)."""
    q, t = torch.as_tensor(q_deg, dtype=torch.float64), torch.as_tensor(tau, dtype=torch.float64)
    cols, blocks = [], []
    parts = []
    if "amap_coef" in maps:
        idx, w = angle_terms(q, torch.as_tensor(maps["amap_coef"]), torch.as_tensor(maps["amap_cover"]))
        parts.append(("angle_map", idx, w, np.asarray(maps["amap_cover"]).any(1), maps["amap_coef"].shape[1]))
    if "lmap_coef" in maps:
        n = maps["lmap_coef"].shape[1]
        idx, w = load_terms(t, torch.as_tensor(maps["lmap_lo"]), torch.as_tensor(maps["lmap_step"]), n - 3)
        parts.append(("load_map", idx, w, np.asarray(maps["lmap_step"]) > 0, n))
    for name, idx, w, on, m in parts:
        for i in np.flatnonzero(on):
            B = np.zeros((len(q), m))
            np.add.at(B, (np.arange(len(q))[:, None], idx[:, i].numpy()), w[:, i].numpy())   # (n, m)
            cols.append((J[:, :, i][:, :, None] * B[:, None, :]).reshape(-1, m))
            blocks.append((name, int(i) + 1, m))
    return (np.hstack(cols) if cols else np.zeros((J.shape[1] * len(q), 0))), blocks


def second_difference(m: int, periodic: bool) -> np.ndarray:
    """(rows, m) second differences of m coefficients (wrapping round when periodic)."""
    if periodic:
        return np.roll(np.eye(m), -1, 1) - 2 * np.eye(m) + np.roll(np.eye(m), 1, 1)
    return np.diff(np.eye(m), 2, axis=0)


def calibration_like(name: str, m: int) -> np.ndarray:
    """(k, m) coefficient vectors of what the calibration already has: a constant angle error (a joint
    offset) for an angle map; a constant and a linear function of the torque (an offset, the
    compliance) for a load map. A uniform cubic B-spline with coefficients c_j = j reproduces u."""
    rows = [np.ones(m)] + ([np.arange(m, dtype=float)] if name == "load_map" else [])
    return np.linalg.qr(np.array(rows).T)[0].T


def layout(train_q_deg: np.ndarray, train_tau: np.ndarray, cfg: dict) -> dict:
    """Zero maps laid out for the training poses: the `parts:` section's angle_map and load_map."""
    a, l = cfg["angle_map"], cfg["load_map"]
    maps = {}
    if a["joints"]:
        n = int(round(360.0 / a["knot_deg"]))
        maps["amap_coef"] = np.zeros((6, n))
        maps["amap_cover"] = coverage(train_q_deg, a["joints"], a["reach_deg"], a["fade_deg"])
    if l["joints"]:
        on = np.isin(np.arange(1, 7), l["joints"])
        lo, hi = train_tau.min(0), train_tau.max(0)
        n = int(l["knots"])
        maps["lmap_lo"] = np.where(on, lo, 0.0)
        maps["lmap_step"] = np.where(on & (hi > lo), (hi - lo) / n, 0.0)
        maps["lmap_coef"] = np.zeros((6, n + 3))
    return maps


def fit(q_deg: np.ndarray, tau: np.ndarray, J: np.ndarray, r: np.ndarray, cfg: dict,
        extra: np.ndarray | None = None) -> tuple[dict, dict, np.ndarray]:
    """Identify the maps of the `parts:` section on the residual r (n, 3) mm at poses q (n, 6) deg with
    gravity torques tau (n, 6) and chain Jacobian J (n, 3, 6), jointly with unpenalised corrections dx
    of the parameters whose Jacobian is `extra` (3n, k): the calibration's, re-estimated beside the
    maps. With measured orientations, r (n, 6) and J (n, 6, 6) carry the weighted orientation rows too
    (identify.residual_rows' layout) and extra is (6n, k). Returns (maps as numpy arrays, a report: each block's rms (arcsec) over the poses and its
    coefficients' posterior standard error, dx (k,))."""
    maps = layout(q_deg, tau, cfg)
    X, blocks = design(q_deg, tau, J, maps)
    E = np.zeros((J.shape[1] * len(q_deg), 0)) if extra is None else extra
    if not blocks:
        return {}, {"blocks": [], "n_coefficients": 0}, np.zeros(E.shape[1])
    noise = cfg["noise_mm"]
    pen = []
    for name, _, m in blocks:
        c, V = cfg[name], calibration_like(name, m)
        D = second_difference(m, name == "angle_map")
        pen.append((noise / (c["prior_arcsec"] * ARCSEC)) ** 2 * np.eye(m)          # size prior
                   + (noise / (c["smooth_arcsec"] * ARCSEC)) ** 2 * D.T @ D          # smoothness prior
                   + (noise / (0.01 * ARCSEC)) ** 2 * V.T @ V)                      # none of the calibration's terms
    P, k = sum(m for *_, m in blocks), E.shape[1]
    Z = np.hstack([X, E])
    A = Z.T @ Z
    o = 0
    for (_, _, m), Pm in zip(blocks, pen):
        A[o:o + m, o:o + m] += Pm
        o += m
    A[P:, P:] += 1e-12 * np.trace(A[P:, P:]) / max(k, 1) * np.eye(k)    # numerically only: dx is free
    sol = np.linalg.solve(A, Z.T @ r.reshape(-1))
    c, dx = sol[:P], sol[P:]
    se = noise * np.sqrt(np.clip(np.diag(np.linalg.inv(A)), 0, None))[:P]
    report, o = {"blocks": []}, 0
    for name, joint, m in blocks:
        key = "amap_coef" if name == "angle_map" else "lmap_coef"
        maps[key][joint - 1] = c[o:o + m]
        contrib = (X[:, o:o + m] @ c[o:o + m]).reshape(len(q_deg), -1)[:, :3]     # its position part
        report["blocks"].append({"part": name, "joint": joint, "coefficients": m,
                                 "displacement_rms_mm": float(np.sqrt((contrib ** 2).sum(1).mean())),
                                 "coef_rms_arcsec": float(np.sqrt((c[o:o + m] ** 2).mean()) / ARCSEC),
                                 "coef_se_arcsec_mean": float(se[o:o + m].mean() / ARCSEC)})
        o += m
    report["n_coefficients"] = P
    return maps, report, dx


def as_geometry(maps: dict) -> dict:
    """The maps as geometry entries (float64 tensors) for kinematics."""
    return {k: torch.as_tensor(np.asarray(v, float), dtype=torch.float64) for k, v in maps.items()}

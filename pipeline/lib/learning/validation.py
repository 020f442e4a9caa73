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
            campaign is left to judge. Only the frame is refitted, not the tool. The
            nominal method's registration is checked like the frame stage's fit
            (frames.check_fit): a mirrored or far-off campaign stops.
    The registration's residual (rms per point, corrected for the parameters fitted) is the part of a
    new campaign's error that no training campaign shows (the tracker set up again, drift, the
    temperature): the model's uncertainty on the campaign is sqrt(uncertainty_mm² + that²) (refit
    modes; `same` adds nothing).
    refit_tool  the tracker moved and the probe may have been re-mounted: as refit, and a tool
            offset dt (flange frame) fitted with each method's frame on the same points, every
            method's marker moved by R_flange(q) dt (its own chain's flange). Only where the
            campaign's orientations fix dt (several tool orientations: the fit's condition
            number is reported); the methods are registered alike. Where the campaign measures
            the probe's orientation, the registration fits it too (the frame, dt and the probe's
            re-mounted rotation dR, weighted by `calibrate.pose_noise`), and each method is judged
            also on the orientation and at every TCP (`judge_poses`, lib/robot/tcp.py).

ISO 9283 position accuracy where the campaign commands one position several
times (a `commanded` column group): per commanded position, with the
deviations d_i = x_i - c_i of the attained marker positions from where the
command put the marker (its orientation may differ between visits),
AP_P = |mean d_i|, the spread mean |d_i - mean d| and ISO's RP = that spread + 3 times its
sample standard deviation, both from the measurements and from each method's predictions, and
bar_error = |predicted mean - measured mean|: how well the method knows where the robot
really goes for that command. Registered in a frame fitted to each method (refit), AP_P measured
is the accuracy after that registration (a constant offset of the robot absorbed).
"""
import numpy as np
import pandas as pd
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from pipeline.lib.learning.metrics import stats
from pipeline.lib.learning.splits import chained
from pipeline.lib.robot.frames import (FRAME_TOOL, MISREAD_PERCENTILE, REFIT_ROUNDS, FrameFitError, check_fit,
                                       determined_beyond, kabsch, kept, robust_kabsch, to_base)
from pipeline.lib.robot.identify import orientation_angles
from pipeline.lib.robot.tcp import pose_errors

METHODS = ("nominal", "calibrated", "calibrated_parts", "model")


def registration_subset(P: np.ndarray, n: int) -> np.ndarray:
    """Bool mask of n points of P (m, 3) spread by farthest-point sampling (deterministic): n distinct points, a
    point measured again (at distance 0 from one chosen) only once every other place is taken."""
    n = min(n, len(P))
    chosen = [int(np.argmin(np.linalg.norm(P - P.mean(0), axis=1)))]
    d = np.linalg.norm(P - P[chosen[0]], axis=1)
    d[chosen[0]] = -1.0                                   # chosen: never again (a repeat's 0 is still above it)
    for _ in range(n - 1):
        chosen.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(P - P[chosen[-1]], axis=1))
        d[chosen] = -1.0
    mask = np.zeros(len(P), bool)
    mask[chosen] = True
    return mask


MODES = ("same", "refit", "refit_tool")


PROBE_ROT = ["tool_rx", "tool_ry", "tool_rz"]


def small_rotation(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """kinematics.rotation_error in numpy: vee of the skew part of A Bᵀ, (k, 3, 3) x2 -> (k, 3) rad."""
    M = A @ np.swapaxes(B, -1, -2)
    return 0.5 * np.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1)


def refit_tool(p: np.ndarray, Rf: np.ndarray, P: np.ndarray, R0: np.ndarray, t0: np.ndarray, rank_tol: float,
               R_probe: np.ndarray | None = None, R_world: np.ndarray | None = None, weight: float = 0.0,
               significance: float = 0.0):
    """Frame and tool offset jointly, P ≈ R (p + Rf dt) + t, from the start (R0, t0): p (k, 3) predicted
    markers, Rf (k, 3, 3) the flange rotations (base frame). Only the offset components the poses'
    orientations determine are fitted (frames.determined_beyond at rank_tol: an offset along an axis
    the flange never turns away from is a translation of the frame); the others stay 0. With measured
    orientations R_world (k, 3, 3, tracker frame) and the predicted ones R_probe, also R R_probe dR ≈ R_world,
    weight mm/rad, and the probe's re-mounted rotation dR. Then, one at a time, the least significant offset
    component whose |estimate| is under `significance` standard errors is held at 0 and the rest refitted
    (backward elimination; 0: none): an offset the registration cannot tell from its noise is no re-mounting,
    only a trade with the frame's translation.
    Returns R, t, dt (3,) mm, dR (3, 3), the names of the components held at 0 and {held: why}."""
    poses = R_world is not None
    names = FRAME_TOOL + (PROBE_ROT if poses else [])

    def residuals(x):
        R = Rotation.from_rotvec(x[:3]).as_matrix()
        r = ((p + np.einsum("kij,j->ki", Rf, x[6:9])) @ R.T + x[3:6] - P).ravel()
        if not poses:
            return r
        dR = Rotation.from_rotvec(x[9:12]).as_matrix()
        return np.r_[r, weight * small_rotation(R @ R_probe @ dR, R_world).ravel()]

    def jacobian(x):                                      # (rows, parameters), forward differences
        r0 = residuals(x)
        steps = [1e-6] * 3 + [1e-3] * 6 + [1e-6] * (len(names) - 9)
        return r0, np.stack([(residuals(x + h * e) - r0) / h for e, h in zip(np.eye(len(names)), steps)], 1)

    def solve(keep):
        def sub(xk):
            x = x0.copy()
            x[keep] = xk
            return residuals(x)
        x = x0.copy()
        x[keep] = least_squares(sub, x0[keep], x_scale="jac").x
        return x

    x0 = np.r_[Rotation.from_matrix(R0).as_rotvec(), t0, np.zeros(len(names) - 6)]
    if poses:                                             # dR starts at the points' mean R_probeᵀ R0ᵀ R_world (from
        d = np.swapaxes(R_probe, -1, -2) @ R0.T @ R_world   # the identity, a probe turned 150° ends at its mirror)
        x0[9:12] = Rotation.from_matrix(d).mean().as_rotvec()
    keep = determined_beyond(jacobian(x0)[1], 6, rank_tol)       # the frame is always fitted
    why = {n: f"not determined by the poses' orientations (pivot below validate.tool_rank_tol = {rank_tol:g})"
           for n, k in zip(names, keep) if not k}
    x = solve(keep)
    while significance > 0 and keep[6:9].any():
        r, J = jacobian(x)
        dof = len(r) - keep.sum()
        if dof <= 0:                                      # nothing left to tell an offset from the noise
            for j in np.flatnonzero(keep[6:9]) + 6:
                keep[j] = False
                why[names[j]] = (f"not testable: {len(r)} residuals for {len(r) - dof} parameters leave no degree "
                                 "of freedom (more validate.register_points)")
            x = solve(keep)
            break
        se = standard_errors(r, J[:, keep], 3 * len(p), dof)
        t = np.abs(x[keep]) / np.maximum(se, 1e-300)
        cand = [(t[i], j) for i, j in enumerate(np.flatnonzero(keep)) if 6 <= j < 9 and t[i] < significance]
        if not cand:
            break
        tj, j = min(cand)
        keep[j] = False
        why[names[j]] = (f"not significant: {x[j]:.3g} mm is {tj:.2f} standard errors of the registration "
                         f"(under validate.tool_significance = {significance:g})")
        x = solve(keep)
    dR = Rotation.from_rotvec(x[9:12]).as_matrix() if poses else np.eye(3)
    return (Rotation.from_rotvec(x[:3]).as_matrix(), x[3:6], x[6:9], dR,
            [n for n, k in zip(names, keep) if not k], why)


def standard_errors(r: np.ndarray, J: np.ndarray, n_position: int, dof: int) -> np.ndarray:
    """(p,) standard errors of a least-squares fit with residuals r (N,) and Jacobian J (N, p) whose first
    n_position rows are positions (mm) and the rest weighted orientations: each group's own variance (its mean
    square, scaled by N / dof), propagated by the sandwich (JᵀJ)⁺ Jᵀ S J (JᵀJ)⁺, so that an orientation residual
    larger or smaller than calibrate.pose_noise says does not decide an offset that only positions see."""
    groups = [slice(0, n_position), slice(n_position, len(r))]
    s2 = np.concatenate([np.full(g.stop - g.start, (r[g] ** 2).mean() if g.stop > g.start else 0.0)
                         for g in groups]) * len(r) / dof
    A = np.linalg.pinv(J.T @ J)
    return np.sqrt(np.clip(np.diag(A @ (J.T * s2) @ J @ A), 0, None))


def judge(pred: dict, P_world: np.ndarray, mode: str, frame: dict, n_register: int, frame_cfg: dict,
          flange_R: dict | None = None, tool_rank_tol: float | None = None, probe_R: dict | None = None,
          R_world: np.ndarray | None = None, weight: float = 0.0, tool_significance: float = 0.0):
    """Each method's 3D error per point and the frame it was judged in.

    pred: {method: (m, 3) base frame}; P_world: (m, 3) tracker frame; flange_R {method: (m, 3, 3)}: the
    flange rotations each method's chain gives (refit_tool). Returns (errors {method: (m,)}, registered
    (m,) bool, frames {method: {"R", "t", "tool_offset_mm"}}); registered points are not judged (their
    errors are the registration residuals). refit_tool: the frame and a tool offset dt (the probe
    re-mounted) on the registration points, every method's prediction moved by R_flange dt; with measured
    orientations R_world (m, 3, 3) and each method's probe orientations probe_R, fitted on them too
    (frames[method]["probe_rotation"]: the re-mounted probe's dR). same: the training frame, refused
    (FrameFitError) where the nominal chain's median error there exceeds frame.max_rms_mm (the tracker moved).
    """
    if mode == "same":
        P = to_base(P_world, frame)
        errors = {m: np.linalg.norm(p - P, axis=1) for m, p in pred.items()}
        off = float(np.median(errors["nominal"])) if "nominal" in errors else 0.0
        if off > frame_cfg["max_rms_mm"]:                  # the frame fit's own limit: no same tracker is that far
            raise FrameFitError(f"frame: same, but in the training frame the nominal chain is {off:.1f} mm (median "
                                f"over {len(P)} points) from the campaign's points, above frame.max_rms_mm = "
                                f"{frame_cfg['max_rms_mm']:g} mm: the tracker moved since training (or this is "
                                "another station's campaign); use frame: refit")
        return (errors, np.zeros(len(P), bool),
                {m: {"R": np.asarray(frame["R"]), "t": np.asarray(frame["t"]), "tool_offset_mm": np.zeros(3)}
                 for m in pred})
    if mode not in MODES:
        raise ValueError(f"params.yaml validate.campaigns.*.frame: {mode!r}; use one of {MODES}")
    reg = registration_subset(P_world, n_register)
    errors, frames = {}, {}
    for m, p in pred.items():
        R, t, inl, _ = robust_kabsch(p[reg], P_world[reg], frame_cfg["outlier_k"], frame_cfg["outlier_min_mm"])
        if m == "nominal":
            check_fit(p[reg][inl], P_world[reg][inl], R, t, "the refit registration (nominal)", frame_cfg)
        frames[m] = {"R": R, "t": t, "tool_offset_mm": np.zeros(3)}
        if mode == "refit_tool":
            poses, at = R_world is not None, np.flatnonzero(reg)
            for _ in range(REFIT_ROUNDS):            # the misreads judged again with the offset: a re-mounted
                k = at[inl]                          # probe's mm of offset widen the first fit's scatter past them
                R, t, dt, dR, held, why = refit_tool(p[k], flange_R[m][k], P_world[k], R, t, tool_rank_tol,
                                                     probe_R[m][k] if poses else None,
                                                     R_world[k] if poses else None, weight, tool_significance)
                r = np.linalg.norm((p[at] + np.einsum("mij,j->mi", flange_R[m][at], dt)) @ R.T + t - P_world[at],
                                   axis=1)
                again = kept(r, inl, frame_cfg["outlier_k"], frame_cfg["outlier_min_mm"])
                if (again == inl).all():
                    break
                inl = again
                R, t = kabsch(p[at[inl]], P_world[at[inl]])
            p = p + np.einsum("mij,j->mi", flange_R[m], dt)
            frames[m] = {"R": R, "t": t, "tool_offset_mm": dt, "tool_held": held, "tool_held_why": why,
                         **({"probe_rotation": dR} if poses else {})}
        errors[m] = np.linalg.norm(p @ R.T + t - P_world, axis=1)
        k = np.flatnonzero(reg)[inl]                      # the registration's own residual, per degree of freedom
        held = frames[m].get("tool_held", FRAME_TOOL[6:])        # refit: no offset fitted
        dof = max(3 * len(k) - 6 - sum(a not in held for a in FRAME_TOOL[6:]), 1)
        frames[m]["registration_rms_mm"] = float(np.sqrt((errors[m][k] ** 2).sum() / dof * 3))
    return errors, reg, frames


def registered_rotations(R_pred: np.ndarray, frame: dict, R_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A method's probe orientations R_pred (n, 3, 3) with its re-mounted probe rotation, and the measured ones
    R_world (n, 3, 3, tracker frame) in the base frame it was registered in (`frame`): the pair to compare."""
    return R_pred @ frame.get("probe_rotation", np.eye(3)), np.einsum("ji,njk->nik", np.asarray(frame["R"]), R_world)


def orientation_percentiles(probe_R: dict, frames: dict, R_world: np.ndarray, judged: np.ndarray) -> dict:
    """Each method's orientation error (arcsec) on the judged points, as judge_poses measures it, at
    frames.MISREAD_PERCENTILE: a statistic a few glitched readings do not move, and half a campaign misread does."""
    out = {}
    for m, R_pred in probe_R.items():
        R_m, R_meas = registered_rotations(R_pred, frames[m], R_world)
        out[m] = float(np.percentile(orientation_angles(R_m[judged], R_meas[judged]), MISREAD_PERCENTILE))
    return out


def judge_poses(pred: dict, probe_R: dict, flange_R: dict, frames: dict, P_world: np.ndarray,
                R_world: np.ndarray, offsets: dict, judged: np.ndarray) -> dict:
    """Each method's orientation and TCP errors (lib/robot/tcp.py pose_errors) on the judged points, in the frame
    it was registered in (its tool offset dt and re-mounted probe rotation dR applied)."""
    out = {}
    for m, p in pred.items():
        f = frames[m]
        p_m = p + np.einsum("mij,j->mi", flange_R[m], f["tool_offset_mm"])
        R_m, R_meas = registered_rotations(probe_R[m], f, R_world)
        out[m] = pose_errors(p_m[judged], R_m[judged], to_base(P_world, f)[judged], R_meas[judged], offsets)
    return out


def coverage(error: np.ndarray, u: np.ndarray, inside: np.ndarray) -> dict:
    """The share of points (n,) whose error is within their uncertainty u, mm: {"all", "in", "out"} of the
    trained workspace (None where there is no point)."""
    return {w: float((error[k] <= u[k]).mean()) if k.any() else None
            for w, k in (("all", np.ones_like(inside)), ("in", inside), ("out", ~inside))}


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
        "uncertainty_coverage": coverage(j.error_model_mm.to_numpy(), j.uncertainty_mm.to_numpy(), inside),
        "angle_map": {"in_range_share": float(j.in_range_angle_map.mean()) if len(j) else None,
                      **{w: {m: stats(j.loc[j.in_range_angle_map == (w == "in"), f"error_{m}_mm"].to_numpy())
                             for m in METHODS} for w in ("in", "out")}},
    }


def same_command(group: np.ndarray, tol: float = 1e-3) -> np.ndarray:
    """Which commanded position each row (m, k) reached, (m,) ids 0.. in the order of the rows' values
    (np.unique's, of each position's first value to 1 µm): rows within tol (1 µm in mm; 1 pm of slack for the
    float) on every column are one position, chained (`splits.chained`: a command read back 0.4 µm off either
    side of a rounding boundary is not two)."""
    _, g = np.unique(np.round(group, 3), axis=0, return_inverse=True)          # (m,) by the value to 1 µm
    comp = chained(group, tol + 1e-9)                                          # (m,) rows within tol
    first = np.full(comp.max() + 1 if len(comp) else 0, len(comp))
    np.minimum.at(first, comp, g.ravel())                                      # each position's first value
    return np.unique(first[comp], return_inverse=True)[1].ravel()


def position_accuracy(commanded: np.ndarray, group: np.ndarray, measured: dict, pred: dict,
                      judged: np.ndarray, registered: bool = False) -> dict:
    """ISO 9283 AP_P and RP per method, measured and predicted, averaged over commanded positions.

    commanded (m, 3): each point's commanded marker position (base frame, mm); group (m, k): what
    was commanded, mm (points whose rows agree to 1 µm reached the same commanded position, maybe in another
    joint configuration and orientation); measured {method: (m, 3) in that method's base frame};
    pred {method: (m, 3)}; registered: that base frame was fitted to the method's own predictions
    (refit, refit_tool), so a constant offset of the robot is absorbed in it: AP_P measured is then
    the accuracy after that registration, not the standard's. A point whose command has an empty cell is
    not judged here; `points_without_command` counts them (absent where there are none). Per position, with deviations
    d_i = x_i - c_i and l_i = |d_i - mean d|: AP_P = |mean d_i|, bar_error = |mean(pred) - mean(measured)|
    over every judged position; over the positions reached at least twice (a campaign that visits
    each position once, as Series_D's cubes, has an AP per position and no RP) the spread mean l_i
    (`rp_*`) and ISO 9283's RP = mean l_i + 3 S_l, S_l the sample standard deviation (n - 1)
    (`rp_iso_*`).
    """
    given = np.isfinite(group).all(1) & np.isfinite(commanded).all(1)     # (m,) an empty command cell: not judged
    commandless, judged = int((judged & ~given).sum()), judged & given
    g = same_command(group[judged])
    c = commanded[judged]
    out = {}
    for m in pred:
        rows = {"ap_measured": [], "ap_predicted": [], "rp_measured": [], "rp_predicted": [], "bar_error": [],
                "rp_iso_measured": [], "rp_iso_predicted": []}
        for k in np.unique(g):
            idx = np.flatnonzero(g == k)
            bars = {}
            for kind, x in (("measured", measured[m][judged][idx]), ("predicted", pred[m][judged][idx])):
                d = x - c[idx]
                bars[kind] = d.mean(0)
                rows[f"ap_{kind}"].append(np.linalg.norm(bars[kind]))
                if len(idx) > 1:
                    l = np.linalg.norm(d - bars[kind], axis=1)          # (n,) each visit from the visits' mean
                    rows[f"rp_{kind}"].append(l.mean())
                    rows[f"rp_iso_{kind}"].append(l.mean() + 3 * l.std(ddof=1))
            rows["bar_error"].append(np.linalg.norm(bars["predicted"] - bars["measured"]))
        out[m] = {"positions": len(rows["ap_measured"]), "positions_repeated": len(rows["rp_measured"]),
                  **{f"{k}_mm": (float(np.mean(v)) if v else None) for k, v in rows.items()},   # means over positions
                  "ap_measured_max_mm": float(np.max(rows["ap_measured"])) if rows["ap_measured"] else None,
                  "rp_iso_measured_max_mm": float(np.max(rows["rp_iso_measured"])) if rows["rp_iso_measured"] else None,
                  "ap_after_registration": registered,
                  **({"points_without_command": commandless} if commandless else {})}
    return out

"""The base-to-world (tracker) transform, P_world = R Q_base + t (eq. 20).

Kabsch/SVD (eqs. 21-26) between the nominal theory points Q and the measured
points P, made robust by iterated rejection of gross outliers (listed, not
hidden). With `frame.estimate_tool`, base frame and tool offset are then
refined jointly by robust least squares on the inliers. Several tracker
stations (campaigns measured from different tracker placements): one frame
each, the tool shared (or, with `frame.tool_per_station`, one per station: a
different marker on each placement), all refined together (`fit_frames`).

`check_fit` stops (FrameFitError) on a fit no real campaign gives: a reflection
(det -1) that fits the points MIRROR_RATIO times better than the best rotation,
which leaves more than `frame.outlier_min_mm` (swapped or mirrored tracker axes:
no rotation undoes them), or an rms above `frame.max_rms_mm` (a wrong unit,
robot model or tool). `fit_frames` checks every station.

`to_base` maps tracker points back into the base frame (inverse of eq. 20).

Where the campaign measures the probe's orientation (the ingest table's meas_q*), `probe_rotation`
finds the probe's rotation in the flange: R_meas = R_frame R_flange(q) R_tool (the rotation half of
the hand-eye problem AX = YB, with the frame's rotation from the positions), as the robust mean of
R_flangeᵀ R_frameᵀ R_meas over the poses (poses beyond median + k·MAD of the scatter left out).
"""
import numpy as np
import scipy.linalg
import torch
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from pipeline.lib.project.columns import MEAS_Q
from pipeline.lib.robot.kinematics import DTYPE, fk_poses, nominal_geometry

REFIT_ROUNDS = 5             # at most this many refits with the outliers judged again at the fitted tool (frame.
                            # estimate_tool) or probe offset (validate's refit_tool)
TOOL_RANK_TOL = 0.01        # refine_with_tool: a tool component whose pivot (determined_beyond: its unit-scaled column,
                            # what the frames explain removed) falls below this is held (validate.tool_rank_tol's value)
MIRROR_RATIO = 3.0          # a reflection this many times better than the best rotation: mirrored axes
MISREAD_PERCENTILE = 90     # orientation columns are judged misread on this percentile of a campaign's scatter: a
                            # wrong Euler sequence can read half of it right (extrinsic zyx on the IPA Series_B and
                            # Series_D, where rx ~ rz: median 397"/470", p90 41 392"/644 027"; read right 420"/617")
FRAME_TOOL = ["rx", "ry", "rz", "tx", "ty", "tz", "tool_x", "tool_y", "tool_z"]   # a frame's and a tool's parameters
CAUSES = ("Likely causes: swapped or mirrored tracker axes (ingest.columns.position, or the tracker's "
          "export), a wrong length unit (ingest.length_unit), a wrong robot model (robot.model) or "
          "tool (robot.tool_mm; a station measured with another marker: frame.tool_per_station)")


class DegenerateFit(ValueError):
    """The points cannot fix a rigid transform (too few, or collinear)."""


class FrameFitError(ValueError):
    """A frame fit no real campaign gives: mirrored tracker axes, or an rms above frame.max_rms_mm."""


def kabsch(Q: np.ndarray, P: np.ndarray, proper: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Rigid transform with P ≈ R Q + t (eqs. 21-26). Q, P: (n, 3) -> R (3, 3), t (3,).

    proper=False: the best orthogonal R, a reflection (det -1) if that fits better.
    """
    Q, P = np.asarray(Q, float), np.asarray(P, float)
    if len(Q) < 3:
        raise DegenerateFit(f"need at least 3 points for a rigid fit, got {len(Q)}")
    q_bar, p_bar = Q.mean(0), P.mean(0)                    # eq. 21
    Qc, Pc = Q - q_bar, P - p_bar                          # eq. 22
    s = np.linalg.svd(Qc, compute_uv=False)
    if s[1] <= 1e-9 * max(s[0], 1e-12):
        raise DegenerateFit(f"points are collinear (singular values {s[0]:.3g}, {s[1]:.3g}, "
                            f"{s[2]:.3g}): a rotation about their line is undetermined")
    H = Qc.T @ Pc / len(Q)                                 # eq. 23
    U, _, Vt = np.linalg.svd(H)                            # eq. 24
    V = Vt.T
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(V @ U.T)) if proper else 1.0])
    R = V @ D @ U.T                                        # eq. 25, det(R) = +1 if proper
    t = p_bar - R @ q_bar                                  # eq. 26
    return R, t


def robust_kabsch(Q, P, k: float = 5.0, min_mm: float = 3.0, max_iter: int = 20):
    """Kabsch with iterated outlier rejection.

    A point is an outlier if its residual exceeds both median + k * 1.4826 * MAD
    of the inliers' residuals and `min_mm`. Returns R, t, inlier mask, residuals (n,).
    """
    inl = np.ones(len(Q), bool)
    for _ in range(max_iter):
        R, t = kabsch(Q[inl], P[inl])
        r = np.linalg.norm(Q @ R.T + t - P, axis=1)
        new = kept(r, inl, k, min_mm)
        if (new == inl).all():
            break
        inl = new
    return R, t, inl, r


def kept(r: np.ndarray, inl: np.ndarray, k: float, min_mm: float) -> np.ndarray:
    """The points (n,) bool whose residual r (n,) exceeds neither median + k * 1.4826 * MAD of the inliers'
    (inl (n,) bool) residuals nor min_mm: the outlier rule of every frame fit here."""
    med = np.median(r[inl])
    mad = 1.4826 * np.median(np.abs(r[inl] - med))
    return r <= max(med + k * mad, min_mm)


def rms(Q, P, R, t) -> float:
    """Root mean square of |R Q + t - P| (mm)."""
    return float(np.sqrt(np.mean(np.sum((Q @ R.T + t - P) ** 2, axis=1))))


def check_fit(Q, P, R, t, where: str, cfg: dict) -> float:
    """The rms of the fit P ≈ R Q + t (the inliers); FrameFitError if a reflection fits MIRROR_RATIO
    times better and the rms is above cfg["outlier_min_mm"] (mirrored axes), or the rms is above
    cfg["max_rms_mm"]. `where` names the fit in the message."""
    found, limit = rms(Q, P, R, t), cfg["max_rms_mm"]
    Rm, tm = kabsch(Q, P, proper=False)
    mirrored = rms(Q, P, Rm, tm)
    if np.linalg.det(Rm) < 0 and found > max(MIRROR_RATIO * mirrored, cfg["outlier_min_mm"]):
        raise FrameFitError(f"{where}: the tracker axes look mirrored or swapped: the best rotation leaves "
                            f"rms {found:.1f} mm on {len(P)} points (frame.max_rms_mm = {limit:g} mm), a "
                            f"reflection (det -1) only {mirrored:.1f} mm; no rotation undoes a swap of two "
                            f"axes or a flipped sign. {CAUSES}")
    if found > limit:
        raise FrameFitError(f"{where}: the frame fit leaves rms {found:.1f} mm on {len(P)} points, above "
                            f"frame.max_rms_mm = {limit:g} mm (nominal kinematics with a real tracker: a few "
                            f"mm). {CAUSES}")
    return found


def flange_poses(q_deg: np.ndarray, geometry: dict) -> tuple[np.ndarray, np.ndarray]:
    """Flange rotations (n, 3, 3) and origins (n, 3) in the base frame."""
    q = torch.as_tensor(np.radians(q_deg), dtype=DTYPE)
    with torch.no_grad():
        T = fk_poses(q, geometry).numpy()
    return T[:, :3, :3], T[:, :3, 3]


def tool_points(Rf, pf, tool) -> np.ndarray:
    """Marker positions (n, 3) in the base frame: Rf_i tool_i + pf_i; tool (3,) or one per pose (n, 3)."""
    return np.einsum("nij,nj->ni", Rf, np.broadcast_to(tool, pf.shape)) + pf


def determined_beyond(J: np.ndarray, n_first: int, rank_tol: float) -> np.ndarray:
    """Which of J's columns after the first n_first (always fitted: a frame) the data determines: (p,) bool,
    True for the first n_first. Columns scaled to unit norm; the rest, with what the first n_first explain
    removed, by column-pivoted QR: a column whose pivot falls below rank_tol is not determined (a tool offset
    along an axis the flange never turns away from is a translation of the frame)."""
    norms = np.linalg.norm(J, axis=0)
    Js = J / np.where(norms > 0, norms, 1.0)
    Qf = np.linalg.qr(Js[:, :n_first])[0]                              # (N, n_first)
    T = Js[:, n_first:] - Qf @ (Qf.T @ Js[:, n_first:])               # (N, p - n_first)
    keep = np.ones(J.shape[1], bool)
    if T.shape[1]:
        _, Rq, piv = scipy.linalg.qr(T, mode="economic", pivoting=True)
        keep[n_first:] = False
        keep[n_first + piv[np.abs(np.diag(Rq)) > rank_tol]] = True
    return keep


def refine_with_tool(Rf, pf, P, frames, tools0, station=None, loss="soft_l1", f_scale=0.5,
                     per_station=False, rank_tol=TOOL_RANK_TOL, labels=None, held_at=None):
    """Jointly fit one base frame per station (rotation vector, t) and the tool offset (shared, or
    with per_station one per station) by robust least squares.

    Model: P_i = R_s (Rf_i tool_s + pf_i) + t_s, s = station[i] (index into frames; None: all 0).
    frames: [(R0, t0)] and tools0 (S, 3) mm starts; labels: the stations' names (for "tool_held"). A tool
    component the poses' flange orientations do not determine (determined_beyond at rank_tol: along an axis
    the flange never turns away from, it is a translation of the frame) is held at held_at (3,) mm (None: its
    start), not left to drift with the frame. Returns [(R, t)], tools (S, 3), diagnostics (with "tool_held":
    {component: why})."""
    S = len(frames)
    station = np.zeros(len(P), int) if station is None else np.asarray(station)
    n_tools = S if per_station else 1
    labels = [str(k) for k in range(S)] if labels is None else labels
    names = [f"{a}{'' if S == 1 else f' (station {labels[k]})'}" for k in range(S) for a in FRAME_TOOL[:6]] + [
        f"{a}{'' if n_tools == 1 else f' (station {labels[k]})'}" for k in range(n_tools) for a in FRAME_TOOL[6:]]

    def unpack(x):
        Rs = Rotation.from_rotvec(x[:6 * S].reshape(S, 6)[:, :3]).as_matrix()      # (S, 3, 3)
        tools = np.broadcast_to(x[6 * S:].reshape(n_tools, 3), (S, 3))              # (S, 3)
        return Rs, x[:6 * S].reshape(S, 6)[:, 3:], tools

    def residuals(x):
        Rs, ts, tools = unpack(x)
        Q = tool_points(Rf, pf, tools[station])
        return (np.einsum("nij,nj->ni", Rs[station], Q) + ts[station] - P).ravel()

    x0 = np.concatenate([np.concatenate([Rotation.from_matrix(R).as_rotvec(), t]) for R, t in frames]
                        + list(np.asarray(tools0, float).reshape(S, 3)[:n_tools]))
    r0 = residuals(x0)                                    # (3n,); forward differences, linear in t and the tool
    J = np.stack([(residuals(x0 + h * e) - r0) / h for e, h in zip(np.eye(len(x0)), ([1e-6] * 3 + [1e-3] * 3) * S
                                                                         + [1e-3] * 3 * n_tools)], 1)
    keep = determined_beyond(J, 6 * S, rank_tol)         # the frames are always fitted
    if held_at is not None:                               # not the last round's fit of it
        x0[6 * S:] = np.where(keep[6 * S:], x0[6 * S:], np.tile(held_at, n_tools))
    held = {n: f"not determined by the poses' flange orientations (pivot below {rank_tol:g}: along an axis the "
               "flange never turns away from, the tool is a translation of the frame): held at robot.tool_mm"
            for n, k in zip(names, keep) if not k}

    def sub(xk):
        x = x0.copy()
        x[keep] = xk
        return residuals(x)
    sol = least_squares(sub, x0[keep], loss=loss, f_scale=f_scale, x_scale="jac")
    x = x0.copy()
    x[keep] = sol.x
    Rs, ts, tools = unpack(x)
    s = np.linalg.svd(sol.jac, compute_uv=False)
    return list(zip(Rs, ts)), tools.copy(), {"condition": float(s[0] / s[-1]), "nfev": int(sol.nfev),
                                             "status": sol.message, "tool_held": held}


def fit_frames(q_deg: np.ndarray, P: np.ndarray, station: np.ndarray, robot, cfg: dict) -> dict:
    """One base-to-world frame per tracker station (and optionally the tool) for measured
    points P (n, 3); station (n,) names, the first one's frame first.

    Each station: robust Kabsch on its points (outliers per station). With
    cfg["estimate_tool"], all frames and one tool (cfg["tool_per_station"]: one per station) are
    then refined jointly on the inliers. Every station's fit is then checked (check_fit).
    Returns {"stations": {name: {"R", "t", "tool_mm", "points": (n,) bool, its points}},
    "inliers" (n,) bool, "residual_mm" (n,), "tool_mm" (the first station's), "method", "condition",
    with estimate_tool "tool_held" {component: why} (refine_with_tool)}.
    """
    station = np.asarray(station)
    names = list(dict.fromkeys(station))
    idx = np.array([names.index(s) for s in station], int)
    Rf, pf = flange_poses(q_deg, nominal_geometry(robot))
    tool = robot.tool.copy()
    Q = tool_points(Rf, pf, tool)                                # nominal theory points (n, 3)
    frames, inl, conds = [], np.zeros(len(P), bool), []
    for k in range(len(names)):
        m = idx == k
        try:
            R, t, inl_k, _ = robust_kabsch(Q[m], P[m], cfg["outlier_k"], cfg["outlier_min_mm"])
        except DegenerateFit as e:                   # too few points, or on a line: which station's
            raise FrameFitError(f"station '{names[k]}': {e}") from None
        frames.append((R, t))
        inl[np.flatnonzero(m)[inl_k]] = True
        sv = np.linalg.svd(Q[m][inl_k] - Q[m][inl_k].mean(0), compute_uv=False)
        conds.append(float(sv[0] / sv[-1]))
    diag = {"method": "kabsch", "condition": max(conds)}
    tools = np.tile(tool, (len(names), 1))                       # (S, 3)
    per_station = cfg["tool_per_station"]
    if per_station and not cfg["estimate_tool"]:
        raise ValueError("params.yaml frame.tool_per_station: true needs frame.estimate_tool: true")
    if cfg["estimate_tool"]:
        for _ in range(REFIT_ROUNDS):                 # the outliers judged again at the fitted tool, until they hold:
            frames, tools, diag = refine_with_tool(Rf[inl], pf[inl], P[inl], frames, tools, idx[inl],   # a tool
                                                   cfg["robust_loss"], cfg["robust_scale_mm"], per_station,  # cm off
                                                   labels=names, held_at=robot.tool)
            Q = tool_points(Rf, pf, tools[idx])                  # hides misreads in the nominal fit's scatter
            Rs, ts = np.stack([R for R, _ in frames]), np.stack([t for _, t in frames])
            r = np.linalg.norm(np.einsum("nij,nj->ni", Rs[idx], Q) + ts[idx] - P, axis=1)
            again = np.zeros(len(P), bool)
            for k in range(len(names)):
                m = idx == k
                again[m] = kept(r[m], inl[m], cfg["outlier_k"], cfg["outlier_min_mm"])
            if (again == inl).all():
                break
            inl = again
        diag["method"] = ("kabsch + least-squares base frame" + ("s" if len(names) > 1 else "")
                          + (" and a tool per station" if per_station else " and tool"))
    Rs, ts = np.stack([R for R, _ in frames]), np.stack([t for _, t in frames])
    r = np.linalg.norm(np.einsum("nij,nj->ni", Rs[idx], Q) + ts[idx] - P, axis=1)
    for k, s in enumerate(names):
        m = (idx == k) & inl
        check_fit(Q[m], P[m], Rs[k], ts[k], f"station '{s}'", cfg)
    return {"stations": {s: {"R": Rs[k], "t": ts[k], "tool_mm": tools[k], "points": idx == k}
                         for k, s in enumerate(names)},
            "inliers": inl, "residual_mm": r, "tool_mm": tools[0], **diag}


def fit_frame(q_deg: np.ndarray, P: np.ndarray, robot, cfg: dict) -> dict:
    """Fit the base-to-world frame (and optionally the tool) to measured points P (n, 3) of one station."""
    fit = fit_frames(q_deg, P, np.zeros(len(P), int), robot, cfg)
    (frame,) = fit.pop("stations").values()
    return {"R": frame["R"], "t": frame["t"], **fit}


def to_base(P_world: np.ndarray, frame: dict) -> np.ndarray:
    """Map world (tracker) points into the base frame: Q = R^T (P - t). frame: {"R", "t"}."""
    R, t = np.asarray(frame["R"]), np.asarray(frame["t"])
    return (P_world - t) @ R


# ----------------------------------------------------------------------------- orientation

ARCSEC = np.pi / (180 * 3600)


def measured_rotations(df) -> np.ndarray | None:
    """The table's measured orientations (n, 3, 3) from its meas_q* columns; None where it has none."""
    if not set(MEAS_Q) <= set(df.columns):
        return None
    return Rotation.from_quat(df[MEAS_Q].to_numpy(float), scalar_first=True).as_matrix()


def quaternions(R: np.ndarray) -> np.ndarray:
    """Rotations (n, 3, 3) as unit quaternions (n, 4), scalar first, qw >= 0 (the meas_q* columns)."""
    qt = Rotation.from_matrix(R).as_quat(scalar_first=True)
    return qt * np.where(qt[:, :1] < 0, -1.0, 1.0)


def probe_rotation(Rf: np.ndarray, R_meas: np.ndarray, k: float = 5.0, max_iter: int = 10):
    """The probe's rotation in the flange from flange rotations Rf (n, 3, 3) and measured orientations R_meas
    (n, 3, 3), both in the base frame: the robust mean of Rfᵀ R_meas. Returns (R_tool (3, 3), its
    [rx, ry, rz] rad (kinematics.rotation_xyz), inlier mask (n,), each pose's scatter about it (n,) arcsec)."""
    each = Rotation.from_matrix(np.einsum("nji,njk->nik", Rf, R_meas))
    inl = np.ones(len(Rf), bool)
    for _ in range(max_iter):
        mean = each[inl].mean()
        dev = (mean.inv() * each).magnitude() / ARCSEC
        med = np.median(dev[inl])
        new = dev <= med + k * 1.4826 * np.median(np.abs(dev[inl] - med))
        if (new == inl).all():
            break
        inl = new
    return mean.as_matrix(), mean.as_euler("xyz"), inl, dev

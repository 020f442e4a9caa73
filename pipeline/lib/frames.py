"""The base-to-world (tracker) transform, P_world = R Q_base + t (eq. 20).

Kabsch/SVD (eqs. 21-26) between the nominal theory points Q and the measured
points P, made robust by iterated rejection of gross outliers (listed, not
hidden). With `frame.estimate_tool`, base frame and tool offset are then
refined jointly by robust least squares on the inliers.

`to_base` maps tracker points back into the base frame (inverse of eq. 20).
"""
import numpy as np
import torch
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .kinematics import DTYPE, fk_poses, nominal_geometry


class DegenerateFit(ValueError):
    """The points cannot fix a rigid transform (too few, or collinear)."""


def kabsch(Q: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid transform with P ≈ R Q + t (eqs. 21-26). Q, P: (n, 3) -> R (3, 3), t (3,)."""
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
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(V @ U.T))])
    R = V @ D @ U.T                                        # eq. 25, det(R) = +1
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
        med = np.median(r[inl])
        mad = 1.4826 * np.median(np.abs(r[inl] - med))
        new = r <= max(med + k * mad, min_mm)
        if (new == inl).all():
            break
        inl = new
    return R, t, inl, r


def flange_poses(q_deg: np.ndarray, geometry: dict) -> tuple[np.ndarray, np.ndarray]:
    """Flange rotations (n, 3, 3) and origins (n, 3) in the base frame."""
    q = torch.as_tensor(np.radians(q_deg), dtype=DTYPE)
    with torch.no_grad():
        T = fk_poses(q, geometry).numpy()
    return T[:, :3, :3], T[:, :3, 3]


def refine_with_tool(Rf, pf, P, R0, t0, tool0, loss="soft_l1", f_scale=0.5):
    """Jointly fit base frame (rotation vector, t) and tool offset by robust least squares.

    Model: P_i = R (Rf_i tool + pf_i) + t. Returns R, t, tool, diagnostics.
    """
    def unpack(x):
        return Rotation.from_rotvec(x[:3]).as_matrix(), x[3:6], x[6:9]

    def residuals(x):
        R, t, tool = unpack(x)
        Q = np.einsum("nij,j->ni", Rf, tool) + pf
        return (Q @ R.T + t - P).ravel()

    x0 = np.concatenate([Rotation.from_matrix(R0).as_rotvec(), t0, tool0])
    sol = least_squares(residuals, x0, loss=loss, f_scale=f_scale, x_scale="jac")
    R, t, tool = unpack(sol.x)
    s = np.linalg.svd(sol.jac, compute_uv=False)
    return R, t, tool, {"condition": float(s[0] / s[-1]), "nfev": int(sol.nfev),
                        "status": sol.message}


def fit_frame(q_deg: np.ndarray, P: np.ndarray, robot, cfg: dict) -> dict:
    """Fit the base-to-world frame (and optionally the tool) to measured points P (n, 3)."""
    g = nominal_geometry(robot)
    Rf, pf = flange_poses(q_deg, g)
    tool = robot.tool.copy()
    Q = np.einsum("nij,j->ni", Rf, tool) + pf                  # nominal theory points (n, 3)
    R, t, inl, r = robust_kabsch(Q, P, cfg["outlier_k"], cfg["outlier_min_mm"])
    s = np.linalg.svd(Q[inl] - Q[inl].mean(0), compute_uv=False)
    diag = {"method": "kabsch", "condition": float(s[0] / s[-1])}
    if cfg["estimate_tool"]:
        R, t, tool, diag = refine_with_tool(Rf[inl], pf[inl], P[inl], R, t, tool,
                                            cfg["robust_loss"], cfg["robust_scale_mm"])
        diag["method"] = "kabsch + least-squares base frame and tool"
        Q = np.einsum("nij,j->ni", Rf, tool) + pf
        r = np.linalg.norm(Q @ R.T + t - P, axis=1)
    return {"R": R, "t": t, "tool_mm": tool, "inliers": inl, "residual_mm": r, **diag}


def to_base(P_world: np.ndarray, frame: dict) -> np.ndarray:
    """Map world (tracker) points into the base frame: Q = R^T (P - t). frame: {"R", "t"}."""
    R, t = np.asarray(frame["R"]), np.asarray(frame["t"])
    return (P_world - t) @ R

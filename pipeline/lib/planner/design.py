"""The planner's D-criterion (docs/planning.md): how much a set of poses tells the calibration.

    Identification      what the calibration identifies (its geometry, parameters, residual sigma)
    information(A)      JᵀJ of a Jacobian A
    prediction(M, ...)  condition number and standard errors from an information matrix
    MapBlock            the angle-map coefficients of the joints a program lacks, with their priors
    map_se              the map block's standard error at the waypoints' angles (arcsec)
    DCriterion          log det(JᵀJ + Λ), updated a pose at a time (greedy D-optimal design)
"""
from dataclasses import dataclass, field

import numpy as np
import torch

from pipeline.lib.robot.errormaps import ARCSEC, calibration_like, cubic_weights, second_difference
from pipeline.lib.robot.identify import geometry_jacobian, is_angular
from pipeline.lib.robot.kinematics import DTYPE, angular_jacobian, fk, fk_jacobian

STATION_NAMES = ["station_rx", "station_ry", "station_rz", "station_tx", "station_ty", "station_tz"]


@dataclass
class Identification:
    """What the calibration identifies: its geometry (calibrated, a kinematics geometry dict), the
    `calibrate:` section, the identified robot parameters' names and the residual sigma (mm, per
    coordinate); new_station: the planned poses are measured from a tracker placement of their own,
    whose 6 frame parameters are identified jointly; weight (mm/rad, identify.orientation_weight): where the
    calibration was fitted on the probe's orientation too, each pose also gives its 3 weighted orientation
    rows, as calibrate's residual does (None: positions only)."""
    geometry: dict
    cfg: dict
    names: list
    sigma_mm: float
    new_station: bool = False
    spec: list = field(default_factory=list)
    weight: float | None = None

    @property
    def k(self) -> int:
        """Rows per pose: 3 (position) or 6 (position and weighted orientation)."""
        return 3 if self.weight is None else 6

    def rows(self, q_deg, new: bool) -> np.ndarray:
        """The identification Jacobian of poses q (n, 6) deg: (n, k, P) mm per parameter unit (rad, mm,
        rad/(N·m)); P = the identified parameters (+ 6 station parameters with new_station, nonzero for
        `new` poses only)."""
        q = torch.as_tensor(np.radians(np.atleast_2d(np.asarray(q_deg, float))), dtype=DTYPE)
        out = []
        for s in range(0, len(q), 512):
            J, self.spec = geometry_jacobian(q[s:s + 512], self.geometry, self.cfg, self.names, self.weight)
            out.append(J.reshape(-1, self.k, J.shape[1]))
        J = np.concatenate(out) if out else np.zeros((0, self.k, len(self.names)))
        if not self.new_station:
            return J
        S = np.zeros((len(q), self.k, 6))
        if new and len(q):
            with torch.no_grad():
                p = fk(q, self.geometry).numpy()
            for k in range(3):                               # d(R(r) p + t)/dr_k at r = 0: e_k x p
                S[:, :3, k] = np.cross(np.eye(3)[k], p)
            S[:, :3, 3:] = np.eye(3)
            if self.weight is not None:                      # R(r) R_probe: the orientation turns by r
                S[:, 3:, :3] = self.weight * np.eye(3)
        return np.concatenate([J, S], axis=2)

    @property
    def parameter_names(self) -> list:
        return list(self.names) + (STATION_NAMES if self.new_station else [])

    def units(self) -> list[tuple[float, str]]:
        """(factor from internal units, report unit) per parameter, as the calibration reports them."""
        out = []
        for name in self.parameter_names:
            if name in STATION_NAMES:
                out.append((np.degrees(1.0), "deg") if name[-2] == "r" else (1.0, "mm"))
                continue
            _, key, i = next(s for s in self.spec if s[0] == name)
            f = np.degrees(1.0) if is_angular(key, i) else 1.0
            out.append((f, "deg/(N·m)" if key == "compliance" else "deg" if f != 1.0 else "mm"))
        return out


def information(A: np.ndarray) -> np.ndarray:
    """JᵀJ of stacked pose rows A (n, k, P)."""
    J = A.reshape(-1, A.shape[-1])
    return J.T @ J


def prediction(M: np.ndarray, ident: Identification, robot_only: bool = False) -> dict:
    """Condition number (column-normalised, as identify.identifiability), log det of the normalised
    matrix, and the standard error sigma sqrt(diag(M⁻¹)) of every parameter, in report units (None
    where M does not identify it). robot_only: the robot's parameters alone (before a new station)."""
    names, units = ident.parameter_names, ident.units()
    if robot_only:
        k = len(ident.names)
        M, names, units = M[:k, :k], names[:k], units[:k]
    d = np.sqrt(np.clip(np.diag(M), 0, None))
    ok = d > 0
    Mn = M[np.ix_(ok, ok)] / np.outer(d[ok], d[ok])
    ev = np.linalg.eigvalsh(Mn) if ok.any() else np.zeros(1)
    full = ok.all() and ev[0] > 1e-14 * ev[-1]
    se = {}
    if full:
        cov = np.linalg.inv(M)
        s = ident.sigma_mm * np.sqrt(np.clip(np.diag(cov), 0, None))
    for k, (name, (f, unit)) in enumerate(zip(names, units)):
        se[name] = {"se": float(s[k] * f) if full else None, "unit": unit}
    return {"condition_number": float(np.sqrt(ev[-1] / ev[0])) if full else None,
            "log_det_normalised": float(np.sum(np.log(np.clip(ev, 1e-300, None)))) if full else None,
            "identified": bool(full), "se": se}


def map_se(block: "MapBlock", crit: "DCriterion", Minv_before: np.ndarray, q_wp, geometry: dict) -> dict:
    """The predicted standard error (arcsec) of each map-block joint's angle error at the waypoints' angles
    (the posterior noise² b M⁻¹ bᵀ of errormaps.fit, b the B-spline weights there), before and after."""
    out = {"joints": block.joints, "noise_mm": block.noise_mm if block.joints else None}
    if not block.joints:
        return out
    q = np.atleast_2d(q_wp)
    n, Pc, s = block.knots, crit.Pc, crit.s
    for b, j in enumerate(block.joints):
        u = np.remainder(q[:, j - 1], 360.0) * n / 360.0
        k = np.floor(u)
        cols = Pc + (k.astype(int)[:, None] + np.arange(4)) % n + b * n                # (w, 4)
        w = cubic_weights(u - k) / s[cols]
        se = lambda Mi: block.noise_mm * np.sqrt(np.einsum("wk,wkl,wl->w", w, Mi[cols[:, :, None], cols[:, None, :]],
                                                           w)) / ARCSEC
        out[f"joint{j}"] = {when: {"mean_arcsec": float(se(Mi).mean()), "max_arcsec": float(se(Mi).max())}
                            for when, Mi in (("before", Minv_before), ("after", crit.Minv))}
    return out


@dataclass
class MapBlock:
    """The angle maps of `joints` (1-based) in the D-criterion: every B-spline coefficient of those joints'
    maps (360 / knot_deg each, rad) with the parts stage's Gaussian priors, as errormaps.fit weighs them
    (a size prior, a smoothness prior, none of a constant joint offset): the correction's part that a
    program outside the maps' coverage needs, and that a new tracker station can confound (a station
    turned about the base axis looks like joint 1's error over the poses it measures)."""
    joints: list
    knot_deg: float
    prior_arcsec: float
    smooth_arcsec: float
    noise_mm: float

    @property
    def knots(self) -> int:
        return int(round(360.0 / self.knot_deg))

    @property
    def size(self) -> int:
        return self.knots * len(self.joints)

    def rows(self, q_deg, geometry: dict, weight: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Sparse rows of poses q (m, 6) deg: values (m, k, 4 per joint) mm/rad and their columns in the
        block: the chain's joint Jacobian (kinematics.fk_jacobian; with weight, below it the weighted
        angular one, as Identification.rows) times each joint's four B-spline weights."""
        q = np.atleast_2d(np.asarray(q_deg, float))
        k = 3 if weight is None else 6
        vals, idx = np.zeros((len(q), k, 4 * len(self.joints))), np.zeros((len(q), 4 * len(self.joints)), int)
        if not self.joints or not len(q):
            return vals, idx
        qt = torch.as_tensor(np.radians(q), dtype=DTYPE)
        with torch.no_grad():
            J = np.concatenate([fk_jacobian(qt[s:s + 512], geometry)[1].numpy() for s in range(0, len(q), 512)])
            if weight is not None:                                             # (m, 6, 6)
                J = np.concatenate([J, weight * np.concatenate(
                    [angular_jacobian(qt[s:s + 512], geometry).numpy() for s in range(0, len(q), 512)])], 1)
        n = self.knots
        for b, j in enumerate(self.joints):
            u = np.remainder(q[:, j - 1], 360.0) * n / 360.0
            k = np.floor(u)
            w = cubic_weights(u - k)                                           # (m, 4)
            idx[:, 4 * b:4 * b + 4] = (k.astype(int)[:, None] + np.arange(4)) % n + b * n
            vals[:, :, 4 * b:4 * b + 4] = J[:, :, j - 1, None] * w[:, None, :]
        return vals, idx

    def precision(self) -> np.ndarray:
        """The priors' precision (size, size) in the units of JᵀJ (errormaps.fit's penalty)."""
        n = self.knots
        one = ((self.noise_mm / (self.prior_arcsec * ARCSEC)) ** 2 * np.eye(n)
               + (self.noise_mm / (self.smooth_arcsec * ARCSEC)) ** 2 * second_difference(n, True).T
               @ second_difference(n, True))
        V = calibration_like("angle_map", n)
        one = one + (self.noise_mm / (0.01 * ARCSEC)) ** 2 * V.T @ V
        out = np.zeros((self.size, self.size))
        for b in range(len(self.joints)):
            out[b * n:(b + 1) * n, b * n:(b + 1) * n] = one
        return out


class DCriterion:
    """log det M, M = JᵀJ + Λ over [the calibration's parameters (+ a new station's), the map block's
    coefficients], Λ the map block's prior (and a 1e-9 ridge), the existing poses in, and its gain for each
    candidate pose (log det(I + A_c M⁻¹ A_cᵀ), A_c the pose's 3 or 6 rows: dense over the calibration's
    columns, 4 per mapped joint over the block's): columns scaled to unit norm for the arithmetic."""

    def __init__(self, A_old: np.ndarray, vals_old, idx_old, A: np.ndarray, vals, idx, prior: np.ndarray):
        self.Pc, self.Pm = A.shape[-1], prior.shape[0]
        col = (A ** 2).sum((0, 1)) + (A_old ** 2).sum((0, 1))
        colm = np.diag(prior).copy()
        for v, i in ((vals, idx), (vals_old, idx_old)):
            np.add.at(colm, i.ravel(), (v ** 2).sum(1).ravel())
        self.s = np.sqrt(np.r_[col, colm])
        self.s[self.s == 0] = 1.0
        self.A, self.vals, self.idx = A / self.s[:self.Pc], vals / self.s[self.Pc + idx][:, None, :], idx
        M = information(self.dense(A_old / self.s[:self.Pc], vals_old / self.s[self.Pc + idx_old][:, None, :],
                                   idx_old))
        M[self.Pc:, self.Pc:] += prior / np.outer(self.s[self.Pc:], self.s[self.Pc:])
        self.M = M + 1e-9 * np.eye(len(M))
        self.Minv = np.linalg.inv(self.M)

    def dense(self, A, vals, idx) -> np.ndarray:
        out = np.zeros((len(A), A.shape[1], self.Pc + self.Pm))
        out[:, :, :self.Pc] = A
        for k in range(idx.shape[1]):
            np.add.at(out, (np.arange(len(A)), slice(None), self.Pc + idx[:, k]), vals[:, :, k])
        return out

    def gains(self, rows: np.ndarray) -> np.ndarray:
        """The log det gain of each candidate in `rows` (indices)."""
        Ac, Am, I = self.A[rows], self.vals[rows], self.Pc + self.idx[rows]
        Mi, Pc = self.Minv, self.Pc
        G = np.eye(Ac.shape[1]) + np.einsum("mip,pq,mjq->mij", Ac, Mi[:Pc, :Pc], Ac)
        if I.shape[1]:
            X = np.einsum("mip,pmk,mjk->mij", Ac, Mi[:Pc][:, I], Am)
            G += X + X.transpose(0, 2, 1) + np.einsum("mik,mkl,mjl->mij", Am, Mi[I[:, :, None], I[:, None, :]], Am)
        return np.linalg.slogdet(G)[1]

    def add(self, c: int) -> None:
        a = self.dense(self.A[c:c + 1], self.vals[c:c + 1], self.idx[c:c + 1])[0]          # (k, P)
        B = self.Minv @ a.T
        self.Minv -= B @ np.linalg.solve(np.eye(len(a)) + a @ B, B.T)
        self.M += a.T @ a

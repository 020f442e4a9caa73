"""What to measure so that a robot program is covered: the measurement planner (docs/planning.md).

Given a program's waypoints (joint configurations), the trained workspace (workspace.py: the training
poses, the network's joint-space radius, the per-joint angle maps' coverage) and the calibration (its
identified parameters, geometry and residual sigma), choose N poses to measure:

candidates   each waypoint's own joints and perturbations of them (`tight`: every joint within
             0.8 x the angle maps' reach; `wide`: joints 1-5 within 0.8 x the network's radius), poses
             sampled in the program's joint box (the waypoints' range widened by a margin), and, for a
             new tracker station, the existing training poses (`link`: measured again from it, they tie
             its frame to the old one); every candidate acceptable (poses.py: joint limits,
             singularities, table and column clearance, the tracker's side when its position is given).
criterion    CRITERION. Greedy, one pose at a time:
             1. coverage: every part of every waypoint that the existing training poses leave
                uncovered, as Workspace.parts defines it (the network: a training pose within the
                radius over joints 1-5; the angle maps: every mapped joint's angle within `reach`
                of a training angle, errormaps.coverage), needs `cover_k` planned poses; the next
                pose is the candidate that satisfies most of the parts still short (ties: the
                larger D-optimality gain);
             2. D-optimality: then the candidate that most raises log det M (DCriterion), M = JᵀJ + Λ
                over the calibration's identified parameters (J: identify.geometry_jacobian at the
                calibrated geometry), a new tracker station's 6 frame parameters (identified jointly:
                they cost information) and the angle-map coefficients of the joints the program
                lacks (MapBlock, with the parts stage's priors Λ: the correction's part), the existing
                training poses and the poses chosen so far in it: a Bayesian D-optimal design.
             `cover=False`: D-optimality alone (the identifiability-only choice).
prediction   the information matrix JᵀJ of the calibration's parameters (and a new station's) before
             (existing poses) and after (with the plan): the condition number of its column-normalised
             form (as identify.identifiability) and the standard error of every identified parameter,
             sigma sqrt(diag((JᵀJ)⁻¹)), sigma the calibration's residual sigma (per coordinate, mm); and
             the map block's standard error at the waypoints' angles (arcsec, map_se).
tour         nearest neighbour in joint space from the pose nearest the program's first waypoint,
             improved by 2-opt; the metric, a step's largest joint move (deg, unwrapped: what a movej
             takes); its travel: the sum of those, and of the steps' joint-space (Euclidean) distances.

Coverage after is computed as if every planned pose were a training pose (the same radius); the
8:1:1 split keeps about one in five out of training, which `cover_k` > 1 absorbs:
`expected_after_split` is the share still covered when each planned pose trains with probability
`train_fraction`.
"""
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from .errormaps import ARCSEC, angle_covered, calibration_like, cubic_weights, second_difference
from .errormaps import coverage as angle_coverage
from .identify import geometry_jacobian, is_angular
from .kinematics import DTYPE, angular_jacobian, fk, fk_jacobian
from .poses import acceptable, checks
from .solvers import min_norm_step
from .workspace import JOINTS, Workspace, wrapped

CRITERION = "coverage_then_d_optimal"
CRITERION_TEXT = ("coverage first (greedy: every uncovered part of every waypoint, as Workspace.parts defines it, "
                  "gets cover_k planned poses), then D-optimality (greedy: maximise log det(JᵀJ + Λ) of the "
                  "calibration's identified parameters, a new station's frame and the uncovered joints' angle-map "
                  "coefficients with their priors Λ; existing training poses included)")
D_ONLY = "d_optimal"
D_ONLY_TEXT = ("D-optimality alone (greedy: maximise log det(JᵀJ + Λ) of the calibration's identified parameters, "
               "a new station's frame and the uncovered joints' angle-map coefficients with their priors Λ)")
STATION_NAMES = ["station_rx", "station_ry", "station_rz", "station_tx", "station_ty", "station_tz"]


# ----------------------------------------------------------------------------- coverage

@dataclass
class Coverage:
    """The trained workspace's coverage, recomputable with more training poses: the existing training
    poses (m, 6) deg, the network's radius (deg), the mapped joints (1-based; [] without maps) and the
    angle maps' reach and fade (deg, the `parts.angle_map` settings)."""
    train_q: np.ndarray
    radius: float
    joints: list
    reach: float
    fade: float

    @classmethod
    def from_workspace(cls, ws: Workspace, reach: float, fade: float) -> "Coverage":
        joints = [] if ws.angle_cover is None else [int(j) + 1 for j in np.flatnonzero(ws.angle_cover.any(1))]
        return cls(np.asarray(ws.train_q, float), float(ws.radius), joints, float(reach), float(fade))

    def workspace(self, extra_q=None) -> Workspace:
        """The workspace as if `extra_q` (k, 6) were training poses too (the radius kept)."""
        q = self.train_q if extra_q is None or len(extra_q) == 0 else np.vstack([self.train_q, extra_q])
        cover = angle_coverage(q, self.joints, self.reach, self.fade) if self.joints else None
        return Workspace(q, self.radius, 0.0, 0.0, 0.0, None, cover)

    def parts(self, q_wp, extra_q=None) -> dict:
        """Workspace.parts of the waypoints q_wp (n, 6) with extra_q trained on: {"network", "angle_map",
        "all"} (n,) bool."""
        if len(self.train_q) == 0 and (extra_q is None or len(extra_q) == 0):
            n = len(np.atleast_2d(q_wp))
            out = {"network": np.zeros(n, bool), "angle_map": np.full(n, not self.joints)}
        else:
            out = self.workspace(extra_q).parts(q_wp)
        out["all"] = out["network"] & out["angle_map"]
        return out

    def requirements(self, q_wp) -> list[tuple[int, str]]:
        """The parts the existing training poses leave uncovered: [(waypoint index, "network" | "joint<i>")]."""
        q = np.atleast_2d(q_wp)
        net = self.parts(q)["network"] if len(self.train_q) else np.zeros(len(q), bool)
        cover = self.workspace().angle_cover if self.joints and len(self.train_q) else np.zeros((6, 360))
        covered = angle_covered(cover, q)                                       # (n, 6)
        out = []
        for w in range(len(q)):
            if not net[w]:
                out.append((w, "network"))
            out += [(w, f"joint{j}") for j in self.joints if not covered[w, j - 1]]
        return out

    def satisfies(self, cand_q, q_wp, reqs) -> np.ndarray:
        """(m, r) bool: candidate pose c, trained on, satisfies requirement r (the same arithmetic as
        Workspace.parts and errormaps.coverage: the network's radius over joints 1-5, wrapped; a
        mapped joint's 1° bin within `reach` of the candidate's angle rounded to 0.1°)."""
        c, q = np.atleast_2d(cand_q), np.atleast_2d(q_wp)
        out = np.zeros((len(c), len(reqs)), bool)
        for k, (w, part) in enumerate(reqs):
            if part == "network":
                out[:, k] = np.linalg.norm(wrapped(c[:, JOINTS] - q[w, JOINTS]), axis=1) <= self.radius
            else:
                j = int(part.removeprefix("joint")) - 1
                b = np.floor(np.remainder(q[w, j], 360.0)) % 360
                s = np.round(np.remainder(c[:, j], 360.0), 1)
                out[:, k] = np.abs((b - s + 180.0) % 360.0 - 180.0) <= self.reach
        return out


# ----------------------------------------------------------------------------- identification

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


# ----------------------------------------------------------------------------- candidates

def program_joints(q0_deg, target, geometry: dict, limits_deg, iterations: int = 30) -> tuple:
    """Joints (n, 6) deg near q0 that put the chain `geometry` on the targets (n, 3) mm (damped
    minimum-norm steps, joint limits kept): where a program given as positions will actually go; and
    how far (n,) mm each stays from its target there (a target it cannot reach stays far)."""
    q = torch.as_tensor(np.radians(np.asarray(q0_deg, float)), dtype=DTYPE)
    t = torch.as_tensor(np.asarray(target, float), dtype=DTYPE)
    lim = torch.as_tensor(np.radians(np.asarray(limits_deg, float)), dtype=DTYPE)
    with torch.no_grad():
        for _ in range(iterations):
            p, J = fk_jacobian(q, geometry)
            q = (q + min_norm_step(J, p - t, 1e-6)).clamp(lim[:, 0], lim[:, 1])
        miss = (fk_jacobian(q, geometry)[0] - t).norm(dim=1)
    return np.degrees(q.numpy()), miss.numpy()


def candidates(q_wp, rng: np.random.Generator, geometry: dict, rules: dict, limits_deg, cov: Coverage,
               per_waypoint: int, region: int, margin_deg: float, tracker_mm=None, link_q=None) -> dict:
    """Acceptable candidate poses: {"q" (m, 6) deg rounded to 1e-6, "near" (m,) the waypoint each was
    made from (-1: not), "kind" (m,) "waypoint" | "tight" | "wide" | "region" | "link", "made": how many
    of each kind were drawn, "rejected_by": {rule: count}}. link_q: poses already measured (the
    training poses) that a new tracker station may measure again, to tie its frame to theirs (at most
    `region` of them, at random). geometry: the nominal chain the rules are judged on (as the twin's
    campaigns are)."""
    q_wp = np.atleast_2d(np.asarray(q_wp, float))
    lim = np.asarray(limits_deg, float)
    tight = 0.8 * cov.reach if cov.joints else 0.2 * cov.radius / np.sqrt(5)
    wide = 0.8 * cov.radius / np.sqrt(5)
    qs, near, kind = [q_wp], [np.arange(len(q_wp))], [np.array(["waypoint"] * len(q_wp), object)]
    k = max(per_waypoint - 1, 0)
    for w in range(len(q_wp)):
        spread = np.where(np.arange(k) % 2 == 0, tight, wide)[:, None]          # alternate tight and wide
        qs.append(q_wp[w] + rng.uniform(-1.0, 1.0, (k, 6)) * spread)
        near.append(np.full(k, w))
        kind.append(np.where(np.arange(k) % 2 == 0, "tight", "wide").astype(object))
    lo = np.maximum(q_wp.min(0) - margin_deg, lim[:, 0])
    hi = np.minimum(q_wp.max(0) + margin_deg, lim[:, 1])
    got, tries = 0, 0
    g = geometry
    while got < region and tries < 20:
        q = np.round(rng.uniform(lo, hi, (4 * region, 6)), 6)
        q = q[acceptable(q, g, rules, lim, tracker_mm=tracker_mm)][:region - got]
        qs.append(q)
        near.append(np.full(len(q), -1))
        kind.append(np.array(["region"] * len(q), object))
        got, tries = got + len(q), tries + 1
    if link_q is not None and len(link_q):
        link = np.asarray(link_q, float)
        qs.append(link[rng.permutation(len(link))[:region]])
        near.append(np.full(len(qs[-1]), -1))
        kind.append(np.array(["link"] * len(qs[-1]), object))
    q, near, kind = np.round(np.concatenate(qs), 6), np.concatenate(near), np.concatenate(kind)
    c = checks(q, g, rules, lim, tracker_mm=tracker_mm)
    ok = np.ones(len(q), bool)
    for v in c.values():
        ok &= v
    made = {kd: int((kind == kd).sum()) for kd in ("waypoint", "tight", "wide", "region", "link")}
    return {"q": q[ok], "near": near[ok], "kind": kind[ok], "made": made,
            "acceptable": {kd: int((ok & (kind == kd)).sum()) for kd in made},
            "rejected_by": {r: int((~v & (kind != "region")).sum()) for r, v in c.items()},
            "waypoints_acceptable": ok[:len(q_wp)]}


# ----------------------------------------------------------------------------- tour

def step_cost(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A move's largest joint move (deg, unwrapped: a movej turns each joint the way its angles say)."""
    return np.abs(a - b).max(-1)


def tour(q_deg: np.ndarray, start: int = 0, passes: int = 50) -> np.ndarray:
    """An open tour through every pose from `start`: nearest neighbour, then 2-opt (segment reversals
    while one shortens the tour), the cost `step_cost`. Returns the visiting order."""
    q = np.asarray(q_deg, float)
    n = len(q)
    if n <= 2:
        return np.r_[start, np.setdiff1d(np.arange(n), [start])].astype(int)[:n]
    D = step_cost(q[:, None], q[None])
    order, free = [start], np.ones(n, bool)
    free[start] = False
    for _ in range(n - 1):
        d = np.where(free, D[order[-1]], np.inf)
        order.append(int(np.argmin(d)))
        free[order[-1]] = False
    order = np.array(order)
    for _ in range(passes):
        better = False
        for i in range(n - 2):                   # reverse order[i+1..j]: edges (i, i+1), (j, j+1) -> (i, j), (i+1, j+1)
            a, b = order[i], order[i + 1]
            j = np.arange(i + 2, n)
            c = order[j]
            nxt = np.where(j + 1 < n, order[np.minimum(j + 1, n - 1)], -1)
            old = D[a, b] + np.where(nxt >= 0, D[c, np.maximum(nxt, 0)], 0.0)
            new = D[a, c] + np.where(nxt >= 0, D[b, np.maximum(nxt, 0)], 0.0)
            gain = old - new
            k = int(np.argmax(gain))
            if gain[k] > 1e-9:
                jj = j[k]
                order[i + 1:jj + 1] = order[i + 1:jj + 1][::-1].copy()
                better = True
        if not better:
            break
    return order


def travel(q_deg: np.ndarray) -> dict:
    """The travel of visiting q (n, 6) deg in order: the sum of each step's largest joint move and of its
    joint-space (Euclidean, 6 joints) distance, degrees."""
    q = np.asarray(q_deg, float)
    d = np.diff(q, axis=0)
    return {"steps": int(len(d)), "max_joint_deg": float(np.abs(d).max(1).sum()) if len(d) else 0.0,
            "joint_space_deg": float(np.linalg.norm(d, axis=1).sum()) if len(d) else 0.0}


# ----------------------------------------------------------------------------- the plan

@dataclass
class Plan:
    """The chosen poses in visiting order, what each was chosen for, and the report (plan.json)."""
    q_deg: np.ndarray               # (N, 6)
    role: list                      # "coverage" | "d_optimal" per pose
    near: list                      # the waypoint index it was made from, or -1
    report: dict


def expected_split_coverage(S: np.ndarray, reqs: list, n_wp: int, covered_before: np.ndarray,
                            train_fraction: float, draws: int = 400) -> float:
    """The share of waypoints covered in every part when each planned pose lands in the train split
    with probability train_fraction: S (N, r) planned pose satisfies requirement r (Monte Carlo, fixed
    seed)."""
    if not reqs:
        return float(covered_before.mean()) if n_wp else 1.0
    rng = np.random.default_rng(0)
    w_of = np.array([w for w, _ in reqs])
    share = 0.0
    for _ in range(draws):
        trained = rng.random(len(S)) < train_fraction
        met = (S & trained[:, None]).any(0)                          # (r,)
        bad = np.zeros(n_wp, bool)
        bad[w_of[~met]] = True
        share += (~bad).mean()
    return float(share / draws)


def plan(q_wp, n: int, cov: Coverage, ident: Identification, cand: dict, cover_k: int = 2,
         cover: bool = True, start_q=None, train_fraction: float = 0.8, maps: MapBlock | None = None) -> Plan:
    """Choose n poses among the candidates `cand` (candidates()) for the program's waypoints q_wp (k, 6)
    deg by CRITERION (cover=False: D_ONLY), order them (tour) and report coverage, identifiability and
    travel (module docstring). start_q: where the tour starts from (default the first waypoint). maps:
    the angle maps' settings (MapBlock); the joints whose coverage the program lacks enter the
    D-criterion with their priors (None: the calibration's parameters alone)."""
    if n < 1:
        raise ValueError(f"plan: n must be at least 1, got {n}")
    q_wp = np.atleast_2d(np.asarray(q_wp, float))
    Q = cand["q"]
    if len(Q) == 0:
        raise ValueError("plan: no acceptable candidate pose (every one breaks a rule: see rejected_by)")
    reqs = cov.requirements(q_wp)
    S = cov.satisfies(Q, q_wp, reqs) if reqs else np.zeros((len(Q), 0), bool)
    need = np.full(len(reqs), cover_k if cover else 0)
    A_old = ident.rows(cov.train_q, new=False) if len(cov.train_q) else np.zeros((0, ident.k, len(ident.parameter_names)))
    A = ident.rows(Q, new=True)
    block = None if maps is None else replace(maps, joints=[j for j in maps.joints
                                                           if any(p == f"joint{j}" for _, p in reqs)])
    block = block if block is not None and block.joints else MapBlock([], 1.0, 1.0, 1.0, 1.0)
    crit = DCriterion(A_old, *block.rows(cov.train_q, ident.geometry, ident.weight), A,
                      *block.rows(Q, ident.geometry, ident.weight),
                      block.precision())
    Minv_before = crit.Minv.copy()
    free = np.ones(len(Q), bool)
    chosen, role = [], []
    for _ in range(min(n, len(Q))):
        gain = np.full(len(Q), -np.inf)
        gain[free] = crit.gains(np.flatnonzero(free))
        score = (S[:, need > 0].sum(1) if (need > 0).any() else np.zeros(len(Q))).astype(float)
        score[~free] = -1
        if score.max() > 0:                                     # coverage: most parts still short, then D
            best = np.flatnonzero(score == score.max())
            c = int(best[np.argmax(gain[best])])
            need = np.maximum(need - S[c], 0)
            role.append("coverage")
        else:
            c = int(np.argmax(gain))
            role.append("d_optimal")
        chosen.append(c)
        free[c] = False
        crit.add(c)
    chosen = np.array(chosen)
    start_q = q_wp[0] if start_q is None else np.asarray(start_q, float)
    first = int(np.argmin(step_cost(Q[chosen], start_q)))
    order = tour(Q[chosen], first)
    nn_travel = travel(Q[chosen][tour(Q[chosen], first, passes=0)])
    chosen, role = chosen[order], [role[i] for i in order]
    q = Q[chosen]

    before, after = cov.parts(q_wp), cov.parts(q_wp, q)
    share = lambda p: {k: float(v.mean()) for k, v in p.items()}
    M_before = information(A_old)
    M_after = M_before + information(A[chosen])
    report = {
        "criterion": {"name": CRITERION if cover else D_ONLY, "text": CRITERION_TEXT if cover else D_ONLY_TEXT,
                      "cover_k": cover_k if cover else 0,
                      "d_optimal_on": ident.parameter_names,
                      "jacobian": "identify.geometry_jacobian at the calibrated geometry (d marker position / "
                                  "d parameter), columns normalised over the existing and candidate poses"},
        "n_requested": int(n), "n_planned": int(len(q)),
        "n_coverage": int(sum(r == "coverage" for r in role)), "n_d_optimal": int(sum(r == "d_optimal" for r in role)),
        "coverage": {
            "radius_deg": cov.radius, "mapped_joints": cov.joints, "reach_deg": cov.reach, "fade_deg": cov.fade,
            "existing_training_poses": int(len(cov.train_q)),
            "before": share(before), "after": share(after),
            "after_expected_split": expected_split_coverage(S[chosen], reqs, len(q_wp), before["all"],
                                                            train_fraction),
            "train_fraction": train_fraction,
            "uncovered_parts_before": len(reqs),
            "parts_short_after": int((S[chosen].sum(0) < max(cover_k, 1)).sum()),
            "per_waypoint": [{"before": {k: bool(v[w]) for k, v in before.items()},
                              "after": {k: bool(v[w]) for k, v in after.items()},
                              "planned_near": int(sum(1 for c in chosen if cand["near"][c] == w))}
                             for w in range(len(q_wp))]},
        "identifiability": {"sigma_mm": ident.sigma_mm, "parameters": ident.parameter_names,
                            "new_station": ident.new_station,
                            "angle_maps": map_se(block, crit, Minv_before, q_wp, ident.geometry),
                            "before": prediction(M_before, ident, robot_only=ident.new_station), "after": prediction(M_after, ident)},
        "travel": {**travel(q), "order": "nearest neighbour from the pose nearest the program's first waypoint, "
                                         "then 2-opt; a step costs its largest joint move",
                   "nearest_neighbour_only": nn_travel},
        "candidates": {"made": cand["made"], "acceptable": cand.get("acceptable", int(len(Q))),
                       "rejected_by": cand["rejected_by"],
                       "chosen": {kd: int((cand["kind"][chosen] == kd).sum()) for kd in np.unique(cand["kind"])},
                       "waypoints_acceptable": int(np.sum(cand["waypoints_acceptable"]))},
    }
    return Plan(q, role, [int(cand["near"][c]) for c in chosen], report)

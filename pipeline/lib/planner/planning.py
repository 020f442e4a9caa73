"""What to measure so that a robot program is covered: the measurement planner (docs/planning.md). The
D-criterion and the prediction live in design.py, the tour in tour.py; here the coverage, the candidates
and the greedy choice.

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
from dataclasses import dataclass, replace

import numpy as np
import torch

from pipeline.lib.planner.design import DCriterion, Identification, MapBlock, information, map_se, prediction
from pipeline.lib.robot.errormaps import angle_covered
from pipeline.lib.robot.errormaps import coverage as angle_coverage
from pipeline.lib.robot.kinematics import DTYPE, fk_jacobian
from pipeline.lib.robot.poses import acceptable, checks
from pipeline.lib.runtime.solvers import min_norm_step
from pipeline.lib.planner.tour import step_cost, tour, travel
from pipeline.lib.learning.workspace import JOINTS, Workspace, wrapped

CRITERION = "coverage_then_d_optimal"
CRITERION_TEXT = ("coverage first (greedy: every uncovered part of every waypoint, as Workspace.parts defines it, "
                  "gets cover_k planned poses), then D-optimality (greedy: maximise log det(JᵀJ + Λ) of the "
                  "calibration's identified parameters, a new station's frame and the uncovered joints' angle-map "
                  "coefficients with their priors Λ; existing training poses included)")
D_ONLY = "d_optimal"
D_ONLY_TEXT = ("D-optimality alone (greedy: maximise log det(JᵀJ + Λ) of the calibration's identified parameters, "
               "a new station's frame and the uncovered joints' angle-map coefficients with their priors Λ)")


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

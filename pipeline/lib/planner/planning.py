"""What to measure so that a robot program is covered: the measurement planner (docs/planning.md). The
D-criterion and the prediction live in design.py, the tour in tour.py, the coverage in coverage.py and
the candidates in candidates.py; here the greedy choice.

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
             With `move_ok`, a move that fails it (poses.moves_clear: the arm through the table or the
             column between two acceptable poses) is taken only where no order avoids it, and then by
             way of a candidate both its ends may move to (`via_deg`); `travel.clearance.failing` holds
             the first move that has none.

Coverage after is computed as if every planned pose were a training pose (the same radius); the
8:1:1 split keeps about one in five out of training, which `cover_k` > 1 absorbs:
`after_expected_split` is the share still covered when each planned pose trains with probability
`train_fraction`.
"""
from dataclasses import dataclass, field, replace

import numpy as np

from pipeline.lib.planner.coverage import Coverage
from pipeline.lib.planner.design import DCriterion, Identification, MapBlock, information, map_se, prediction
from pipeline.lib.planner.tour import once_a_pair, step_cost, tour, travel, vias

CRITERION = "coverage_then_d_optimal"
CRITERION_TEXT = ("coverage first (greedy: every uncovered part of every waypoint, as Workspace.parts defines it, "
                  "gets cover_k planned poses), then D-optimality (greedy: maximise log det(JᵀJ + Λ) of the "
                  "calibration's identified parameters, a new station's frame and the uncovered joints' angle-map "
                  "coefficients with their priors Λ; existing training poses included)")
D_ONLY = "d_optimal"
D_ONLY_TEXT = ("D-optimality alone (greedy: maximise log det(JᵀJ + Λ) of the calibration's identified parameters, "
               "a new station's frame and the uncovered joints' angle-map coefficients with their priors Λ)")


# ----------------------------------------------------------------------------- the plan

@dataclass
class Plan:
    """The chosen poses in visiting order, what each was chosen for, and the report (plan.json)."""
    q_deg: np.ndarray               # (N, 6)
    role: list                      # "coverage" | "d_optimal" per pose
    near: list                      # the waypoint index it was made from, or -1
    report: dict
    via_deg: dict = field(default_factory=dict)     # {k: (6,)}: a pose passed through between poses k and k + 1


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
         cover: bool = True, start_q=None, train_fraction: float = 0.8, maps: MapBlock | None = None,
         move_ok=None) -> Plan:
    """Choose n poses among the candidates `cand` (candidates()) for the program's waypoints q_wp (k, 6)
    deg by CRITERION (cover=False: D_ONLY), order them (tour) and report coverage, identifiability and
    travel (module docstring). start_q: where the tour starts from (default the first waypoint). maps:
    the angle maps' settings (MapBlock); the joints whose coverage the program lacks enter the
    D-criterion with their priors (None: the calibration's parameters alone). move_ok(q_from (6,), q_to (6,))
    -> bool: the moves the tour may take (None: any)."""
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
    move_ok = None if move_ok is None else once_a_pair(move_ok)
    order = tour(Q[chosen], first, move_ok=move_ok)
    nn_travel = travel(Q[chosen][tour(Q[chosen], first, passes=0, move_ok=move_ok)])
    chosen, role = chosen[order], [role[i] for i in order]
    q = Q[chosen]
    via = {} if move_ok is None else vias(q, Q, move_ok)
    path = np.concatenate([np.vstack([q[k]] + ([via[k]] if via.get(k) is not None else [])) for k in range(len(q))])

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
        "travel": {**travel(path), "order": "nearest neighbour from the pose nearest the program's first waypoint, "
                                            "then 2-opt; a step costs its largest joint move",
                   "nearest_neighbour_only": nn_travel,
                   "clearance": {"checked": move_ok is not None,
                                 "via": [{"after": k, "j_deg": v.tolist()} for k, v in via.items() if v is not None],
                                 "failing": [[k, k + 1] for k, v in via.items() if v is None]}},
        "candidates": {"made": cand["made"], "acceptable": cand.get("acceptable", int(len(Q))),
                       "rejected_by": cand["rejected_by"],
                       "chosen": {kd: int((cand["kind"][chosen] == kd).sum()) for kd in np.unique(cand["kind"])},
                       "waypoints_acceptable": int(np.sum(cand["waypoints_acceptable"]))},
    }
    return Plan(q, role, [int(cand["near"][c]) for c in chosen], report,
                {k: v for k, v in via.items() if v is not None})

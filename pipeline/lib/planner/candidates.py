"""The poses the planner may choose from: each waypoint's own joints and perturbations of them, poses in
the program's joint box and, for a new tracker station, the training poses again; every one acceptable
(docs/planning.md). And where a program given as positions will actually go (program_joints), by the program
compensator's configuration rule (waypoints.another_configuration)."""
import numpy as np
import torch

from pipeline.lib.planner.coverage import Coverage
from pipeline.lib.robot.kinematics import DTYPE, fk_jacobian
from pipeline.lib.robot.poses import acceptable, checks
from pipeline.lib.runtime.solvers import min_norm_step
from pipeline.lib.runtime.waypoints import another_configuration


MAX_STEP_RAD = 0.1              # program_joints: a joint turns at most this far an iteration (from a singular start,
                                # UR's home, an undamped step spun joints past 360°)


def program_joints(q0_deg, target, geometry: dict, limits_deg, iterations: int = 100) -> tuple:
    """Joints (n, 6) deg near q0 that put the chain `geometry` on the targets (n, 3) mm (damped
    minimum-norm steps of at most MAX_STEP_RAD a joint, joint limits kept): where a program given as positions
    will actually go; how far (n,) mm each stays from its target there (a target it cannot reach stays far);
    and, per waypoint, why those joints are another configuration than q0's, or None
    (waypoints.another_configuration, position targets: the wrist free), the rule by which the program
    compensator refuses such a waypoint."""
    q = torch.as_tensor(np.radians(np.asarray(q0_deg, float)), dtype=DTYPE)
    t = torch.tensor(np.asarray(target, float), dtype=DTYPE)              # a copy: a table's column may be read-only
    lim = torch.as_tensor(np.radians(np.asarray(limits_deg, float)), dtype=DTYPE)
    with torch.no_grad():
        for _ in range(iterations):
            p, J = fk_jacobian(q, geometry)
            step = min_norm_step(J, p - t, 1e-6)                               # (n, 6) rad
            step = step * (MAX_STEP_RAD / step.abs().amax(1, keepdim=True).clamp(min=MAX_STEP_RAD))
            q = (q + step).clamp(lim[:, 0], lim[:, 1])
        miss = (fk_jacobian(q, geometry)[0] - t).norm(dim=1)
    q_deg = np.degrees(q.numpy())
    return q_deg, miss.numpy(), another_configuration(q0_deg, q_deg, geometry, orientation=False)


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

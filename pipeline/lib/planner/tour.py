"""The order to measure poses in: an open tour, nearest neighbour then 2-opt, in joint space (the
measurement planner's, docs/planning.md)."""
import numpy as np


def step_cost(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A move's largest joint move (deg, unwrapped: a movej turns each joint the way its angles say)."""
    return np.abs(a - b).max(-1)


BLOCKED_DEG = 1e6                   # what a move that fails move_ok costs on top: taken only where no other is left


def tour(q_deg: np.ndarray, start: int = 0, passes: int = 50, move_ok=None) -> np.ndarray:
    """An open tour through every pose from `start`: nearest neighbour, then 2-opt (segment reversals
    while one shortens the tour), the cost `step_cost`. With move_ok(q_from (6,), q_to (6,)) -> bool, asked
    lazily (once a pair), a move that fails it is taken only where no other is left: nearest neighbour
    takes the nearest pose it may move to, and 2-opt makes no move that fails it and costs a failing one
    BLOCKED_DEG more. Returns the visiting order."""
    q = np.asarray(q_deg, float)
    n = len(q)
    if n <= 2:
        return np.r_[start, np.setdiff1d(np.arange(n), [start])].astype(int)[:n]
    D = step_cost(q[:, None], q[None])
    known = {}

    def ok(i, j):                              # the move i <-> j passes move_ok; a failing one costs more
        if move_ok is None:
            return True
        key = (min(i, j), max(i, j))
        if key not in known:
            known[key] = bool(move_ok(q[key[0]], q[key[1]]))
            if not known[key]:
                D[i, j] = D[j, i] = D[i, j] + BLOCKED_DEG
        return known[key]

    order, free = [start], np.ones(n, bool)
    free[start] = False
    for _ in range(n - 1):
        d = np.where(free, D[order[-1]], np.inf)
        near = np.argsort(d, kind="stable")[:int(free.sum())]
        order.append(int(next((c for c in near if ok(order[-1], int(c))), near[0])))
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
            for k in np.argsort(-gain, kind="stable"):
                if gain[k] <= 1e-9:
                    break
                if ok(a, c[k]) and (nxt[k] < 0 or ok(b, nxt[k])):
                    jj = j[k]
                    order[i + 1:jj + 1] = order[i + 1:jj + 1][::-1].copy()
                    better = True
                    break
        if not better:
            break
    return order


def once_a_pair(move_ok):
    """move_ok(q_from (6,), q_to (6,)) -> bool asked once for each pair of poses (in either order): the tours
    and `vias` of one plan ask about the same moves."""
    seen = {}

    def ok(a, b):
        key = tuple(sorted((np.asarray(a, float).tobytes(), np.asarray(b, float).tobytes())))
        if key not in seen:
            seen[key] = bool(move_ok(a, b))
        return seen[key]
    return ok


def vias(q_deg: np.ndarray, pool_deg: np.ndarray, move_ok) -> dict:
    """{k: via (6,) deg} for each step k (q[k] -> q[k + 1]) of visiting q (n, 6) deg in order that fails
    move_ok: the pose of pool (m, 6) deg that both ends may move to and back from, the nearest to both
    (`step_cost` summed). It stops at the first such step the pool has none for: {k: None} is its last entry."""
    q, pool = np.asarray(q_deg, float), np.asarray(pool_deg, float)
    out = {}
    for k in range(len(q) - 1):
        if move_ok(q[k], q[k + 1]):
            continue
        cost = step_cost(pool, q[k]) + step_cost(pool, q[k + 1])
        out[k] = next((pool[w] for w in np.argsort(cost, kind="stable")
                       if move_ok(q[k], pool[w]) and move_ok(pool[w], q[k + 1])), None)
        if out[k] is None:
            break
    return out


def travel(q_deg: np.ndarray) -> dict:
    """The travel of visiting q (n, 6) deg in order: the sum of each step's largest joint move and of its
    joint-space (Euclidean, 6 joints) distance, degrees."""
    q = np.asarray(q_deg, float)
    d = np.diff(q, axis=0)
    return {"steps": int(len(d)), "max_joint_deg": float(np.abs(d).max(1).sum()) if len(d) else 0.0,
            "joint_space_deg": float(np.linalg.norm(d, axis=1).sum()) if len(d) else 0.0}

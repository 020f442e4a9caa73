"""The order to measure poses in: an open tour, nearest neighbour then 2-opt, in joint space (the
measurement planner's, docs/planning.md)."""
import numpy as np


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

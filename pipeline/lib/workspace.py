"""Where the model was trained, and how wrong it expects to be: `in_workspace` and `uncertainty_mm`.

Coverage is measured in joint space, on joints 1-5 (`JOINTS`): the network
reads joint angles, so a pose is familiar when a training pose had nearly the
same angles. Joint 6 is left out: it turns the flange about its own axis and
moves the marker only through the sub-mm tool offset, so a training set need
not cover it. Angles are wrapped: 350° and -10° are the same angle.

    d(q)          distance (deg, Euclidean over joints 1-5, wrapped) from q to the nearest training pose
    radius_deg    the `radius_quantile` of the training poses' own nearest-neighbour distances (leave
                  one out): how far apart training poses are where they do cover the space
    in_workspace  d(q) <= radius_deg
    uncertainty   u0 * max(1, d(q) / radius_deg), u0 = the `coverage` quantile of the model's
                  validation-split 3D errors: inside, the model errs less than u0 on that share of poses;
                  outside, the estimate grows with the distance (the network extrapolates, the
                  error it adds grows with it). Its coverage is measured, not assumed (validate, report).
"""
import numpy as np

JOINTS = [0, 1, 2, 3, 4]                                   # joints 1-5 (0-based)


def wrapped(a_deg: np.ndarray) -> np.ndarray:
    """Angle differences wrapped to (-180, 180] degrees."""
    return (np.asarray(a_deg, float) + 180.0) % 360.0 - 180.0


def nearest_distance(q_deg: np.ndarray, ref_deg: np.ndarray, chunk: int = 2048,
                     leave_one_out: bool = False) -> np.ndarray:
    """Distance (deg) from each pose q (n, 6) to the nearest of ref (m, 6), over JOINTS, wrapped."""
    q, ref = np.asarray(q_deg, float)[:, JOINTS], np.asarray(ref_deg, float)[:, JOINTS]
    out = np.empty(len(q))
    for s in range(0, len(q), chunk):
        d = np.linalg.norm(wrapped(q[s:s + chunk, None] - ref[None]), axis=-1)   # (c, m)
        if leave_one_out:
            d[np.arange(len(d)), s + np.arange(len(d))] = np.inf
        out[s:s + chunk] = d.min(1)
    return out


class Workspace:
    """The training poses' coverage and the model's error scale; JSON-able via `to_dict`."""

    def __init__(self, train_q_deg, radius_deg: float, u0_mm: float):
        self.train_q = np.asarray(train_q_deg, float)          # (m, 6)
        self.radius, self.u0 = float(radius_deg), float(u0_mm)

    @classmethod
    def fit(cls, train_q_deg, val_error_mm, cfg: dict) -> "Workspace":
        """From the training poses (m, 6) deg, the model's 3D errors (mm) on the validation split and
        the `workspace:` section (radius_quantile, coverage)."""
        nn = nearest_distance(train_q_deg, train_q_deg, leave_one_out=True)
        return cls(train_q_deg, np.quantile(nn, cfg["radius_quantile"]),
                   np.quantile(val_error_mm, cfg["coverage"]))

    def distance(self, q_deg) -> np.ndarray:
        return nearest_distance(np.atleast_2d(q_deg), self.train_q)

    def __call__(self, q_deg) -> tuple[np.ndarray, np.ndarray]:
        """Poses (n, 6) deg -> (uncertainty_mm (n,), in_workspace (n,) bool)."""
        d = self.distance(q_deg)
        return self.u0 * np.maximum(1.0, d / self.radius), d <= self.radius

    def to_dict(self) -> dict:
        return {"joints": [j + 1 for j in JOINTS], "radius_deg": self.radius, "u0_mm": self.u0,
                "train_q_deg": self.train_q.round(6).tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Workspace":
        return cls(d["train_q_deg"], d["radius_deg"], d["u0_mm"])

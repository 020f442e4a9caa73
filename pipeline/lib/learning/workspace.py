"""Where the model was trained, and how wrong it expects to be: `in_workspace` and `uncertainty_mm`.

Coverage is measured in joint space, on joints 1-5 (`JOINTS`): the network
reads joint angles, so a pose is familiar when a training pose had nearly the
same angles. Joint 6 is left out: it turns the flange about its own axis and
moves the marker only through the sub-mm tool offset, so a training set need
not cover it. Angles are wrapped: 350° and -10° are the same angle.

    d(q)          distance (deg, Euclidean over joints 1-5, wrapped) from q to the nearest training pose
    radius_deg    the `radius_quantile` of the training poses' own nearest-neighbour distances (leave
                  one out): how far apart training poses are where they do cover the space
    in_workspace  d(q) <= radius_deg (the network's coverage)
    uncertainty   the `coverage` quantile of the validation-split 3D errors of what holds at q: the
                  whole model within the radius; the calibration with its per-joint error maps
                  (errormaps.py) where the network has faded (the maps hold wherever each mapped
                  joint's angle was measured); the calibration alone where a mapped joint was
                  not; blended by the fade weight. Its coverage is measured, not assumed
                  (validate, report).
    fade(q)       the network's correction weight (`Fade`, inside BoTER): 1 within radius_deg,
                  falling linearly to 0 at `fade_to` radii, so far from every training pose the
                  model is the calibrated physics it sits on.
"""
import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import nn

from pipeline.lib.robot.errormaps import angle_covered

JOINTS = [0, 1, 2, 3, 4]                                   # joints 1-5 (0-based)
TREE_ROWS, NEAREST_K = 64, 4                               # nearest_distance: the KD-tree from 64 poses on, 4 candidates


def wrapped(a_deg):
    """Angle differences wrapped to [-180, 180) degrees (numpy or torch)."""
    return (a_deg + 180.0) % 360.0 - 180.0


def nearest_distance(q_deg, ref_deg, chunk: int = 256, leave_one_out: bool = False):
    """Distance (deg) from each pose q (n, 6) to the nearest of ref (m, 6), over JOINTS, wrapped.

    Tensors in, a tensor out (differentiable, exportable); arrays in, an array out, computed in numpy (in
    the service, right after an onnxruntime run, a pose's check cost 0.32 ms in torch, 0.05 in numpy).
    From TREE_ROWS poses on, scipy's periodic KD-tree hands each pose its NEAREST_K nearest candidates and
    the formula picks among them (`candidates`: the same numbers, ~10× faster at m = 576); otherwise
    `chunk` poses at a time against all of ref, a (chunk, m, 5) block that stays in the cache (256: 2-3×
    faster than 1024 with the same numbers, docs/decisions.md).
    """
    if not isinstance(q_deg, torch.Tensor):
        q, ref = np.asarray(q_deg, float)[:, JOINTS], np.asarray(ref_deg, float)[:, JOINTS]
        near = None if leave_one_out else candidates(q, ref)                    # (n, k) or None
        out = np.empty(len(q))
        for s in range(0, len(q), chunk):
            others = ref[None] if near is None else ref[near[s:s + chunk]]     # (1, m, 5) or (c, k, 5)
            d = q[s:s + chunk, None] - others                                   # (c, m, 5), in place:
            d += 180.0                                                          # wrapped(d) ** 2, with
            np.fmod(d, 360.0, out=d)                                            # np.mod's numbers (fmod
            np.add(d, 360.0, out=d, where=d < 0)                                # is exact; the sign fix
            d -= 180.0                                                          # is np.mod's own), 2x
            d *= d                                                              # faster
            d = np.sqrt(d.sum(-1))                                              # (c, m)
            if leave_one_out:
                d[np.arange(len(d)), s + np.arange(len(d))] = np.inf
            out[s:s + chunk] = d.min(1)
        return out
    q, ref = q_deg[:, JOINTS], torch.as_tensor(ref_deg)[:, JOINTS].to(q_deg.dtype)
    if torch.compiler.is_exporting():                       # ONNX export: one chunk, the batch size stays free
        return wrapped(q[:, None] - ref[None]).norm(dim=-1).min(1).values
    near = None if leave_one_out else candidates(q.detach().cpu().numpy(), ref.cpu().numpy())
    if near is not None:
        others = ref[torch.as_tensor(near, device=ref.device)]                  # (n, k, 5)
        return wrapped(q[:, None] - others).norm(dim=-1).min(1).values
    out = []
    for s in range(0, len(q), chunk):
        d = wrapped(q[s:s + chunk, None] - ref[None]).norm(dim=-1)               # (c, m)
        if leave_one_out:
            d[torch.arange(len(d)), s + torch.arange(len(d))] = torch.inf
        out.append(d.min(1).values)
    return torch.cat(out)


def candidates(q, ref):
    """(n, k) indices of each pose's k = NEAREST_K nearest in ref, q (n, 5) and ref (m, 5) deg, found by
    scipy's KD-tree on the torus of wrapped angles (boxsize 360); None where brute force is as cheap or must
    answer: fewer than TREE_ROWS poses, ref no larger than k, a non-finite angle. The exact formula then
    picks among the k, so the distance is the brute force's to the bit unless k + 1 poses of ref tie within
    rounding (the tree's arithmetic is not the formula's)."""
    k = NEAREST_K
    if len(q) < TREE_ROWS or len(ref) <= k or not (np.isfinite(q).all() and np.isfinite(ref).all()):
        return None
    _, idx = cKDTree(on_torus(ref), boxsize=360.0).query(on_torus(q), k=k)
    return idx


def on_torus(a):
    """Angles (deg) mapped into [0, 360), as the periodic KD-tree needs (np.mod may round up to 360)."""
    a = np.mod(a, 360.0)
    a[a >= 360.0] = 0.0
    return a


def workspace_radius(train_q_deg, quantile: float) -> float:
    """The `radius_quantile` of the training poses' own (leave-one-out) nearest-neighbour distances."""
    return float(np.quantile(nearest_distance(train_q_deg, train_q_deg, leave_one_out=True), quantile))


class Fade(nn.Module):
    """Weight of the network's correction: 1 within `radius` (deg) of a training pose, 0 beyond
    `fade_to` radii, linear between; fade_to None: always 1 (the paper's model). Buffers, so the
    training poses travel with the weights (sized from the state dict on load)."""

    def __init__(self, fade_to: float | None):
        super().__init__()
        self.fade_to = fade_to
        self.register_buffer("ref", torch.zeros(0, 6, dtype=torch.float64))   # (m, 6) deg
        self.register_buffer("radius", torch.tensor(np.inf, dtype=torch.float64))

    def fit(self, train_q_deg, radius_deg: float) -> None:
        self.ref = torch.as_tensor(np.array(train_q_deg, float))
        self.radius = torch.tensor(float(radius_deg), dtype=torch.float64)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        if prefix + "ref" in state_dict:                    # the saved training poses set the size
            self.ref = torch.empty_like(state_dict[prefix + "ref"])
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def forward(self, q):                                   # (B, 6) rad -> (B, 1)
        if self.fade_to is None or len(self.ref) == 0:
            return torch.ones_like(q[:, :1])                # not len(q): an export would fix the batch size
        d = nearest_distance(torch.rad2deg(q.double()), self.ref) / self.radius     # (B,) in radii
        return ((self.fade_to - d) / (self.fade_to - 1.0)).clamp(0.0, 1.0)[:, None].to(q.dtype)


class Workspace:
    """Where each part of the correction holds, and the model's error scale; JSON-able via `to_dict`.

    Parts: the network (joint-space radius, `in_workspace`) and the per-joint angle maps (each mapped
    joint's angle inside its trained coverage, `angle_cover`: errormaps.coverage). uncertainty_mm is
    the error scale of what holds at the pose: u_model (the whole model, validation split) where the
    network is in full, u_parts (the calibration with the error maps) where it has faded, u_calibrated
    (the calibration alone) where a mapped joint lies outside its coverage, blended by the network's
    fade weight (Fade) between its radius and fade_to radii. `network` False (it did not lower the
    validation error, evaluate's verdict): the network holds nowhere, the physics' scale everywhere, and
    what is served, compensated and exported is the physics alone (model.served).
    """

    def __init__(self, train_q_deg, radius_deg: float, u_model_mm: float, u_parts_mm: float,
                 u_calibrated_mm: float, fade_to: float | None, angle_cover=None, network: bool = True):
        self.train_q = np.asarray(train_q_deg, float)          # (m, 6)
        self.radius, self.u0 = float(radius_deg), float(u_model_mm)
        self.u_parts, self.u_cal, self.fade_to = float(u_parts_mm), float(u_calibrated_mm), fade_to
        self.angle_cover = None if angle_cover is None else np.asarray(angle_cover, float)   # (6, 360)
        self.network = bool(network)     # kept: it lowered the validation error; else it holds nowhere

    @classmethod
    def fit(cls, train_q_deg, val_errors_mm: dict, cfg: dict, fade_to, angle_cover=None,
            network: bool = True) -> "Workspace":
        """From the training poses (m, 6) deg, the validation split's 3D errors (mm) of "model",
        "calibrated_parts" and "calibrated", the `workspace:` section (radius_quantile, coverage), the
        model's fade_to, the angle maps' coverage (None: no maps) and whether the network is kept."""
        q = lambda k: float(np.quantile(val_errors_mm[k], cfg["coverage"]))
        return cls(train_q_deg, workspace_radius(train_q_deg, cfg["radius_quantile"]), q("model"),
                   q("calibrated_parts"), q("calibrated"), fade_to, angle_cover, network)

    def distance(self, q_deg) -> np.ndarray:
        return nearest_distance(np.atleast_2d(q_deg), self.train_q)

    def parts(self, q_deg) -> dict:
        """Per pose (n,) bool: inside the network's workspace ("network") and every mapped joint inside
        its angle map's coverage ("angle_map"; all True without maps)."""
        q = np.atleast_2d(np.asarray(q_deg, float))
        return {"network": self.distance(q) <= self.radius, "angle_map": self.angle_map(q)}

    def angle_map(self, q_deg) -> np.ndarray:
        """(n,) bool: every mapped joint's angle inside its map's coverage (all True without maps)."""
        q = np.atleast_2d(np.asarray(q_deg, float))
        if self.angle_cover is None:
            return np.ones(len(q), bool)
        return angle_covered(self.angle_cover, q)[:, self.angle_cover.any(1)].all(1)

    def __call__(self, q_deg) -> tuple[np.ndarray, np.ndarray]:
        """Poses (n, 6) deg -> (uncertainty_mm (n,), in_workspace (n,) bool: the network's)."""
        q = np.atleast_2d(np.asarray(q_deg, float))
        d = self.distance(q) / self.radius                     # radii
        w = np.ones(len(q)) if self.fade_to is None else np.clip((self.fade_to - d) / (self.fade_to - 1.0), 0, 1)
        w = w if self.network else np.zeros(len(q))
        u_phys = np.where(self.angle_map(q), self.u_parts, self.u_cal)
        return w * self.u0 + (1 - w) * u_phys, d <= 1.0

    def to_dict(self) -> dict:
        return {"joints": [j + 1 for j in JOINTS], "radius_deg": self.radius, "u_model_mm": self.u0,
                "u_parts_mm": self.u_parts, "u_calibrated_mm": self.u_cal, "fade_to": self.fade_to,
                "angle_cover": None if self.angle_cover is None else self.angle_cover.round(6).tolist(),
                "train_q_deg": self.train_q.round(6).tolist(), "network": self.network}

    @classmethod
    def from_dict(cls, d: dict) -> "Workspace":
        return cls(d["train_q_deg"], d["radius_deg"], d["u_model_mm"], d["u_parts_mm"], d["u_calibrated_mm"],
                   d["fade_to"], d["angle_cover"], d.get("network", True))

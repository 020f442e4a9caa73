"""The trained workspace's coverage of a program's waypoints, recomputable as if more poses were trained
on: what the planner must cover first (docs/planning.md)."""
from dataclasses import dataclass

import numpy as np

from pipeline.lib.learning.workspace import JOINTS, Workspace, wrapped
from pipeline.lib.robot.errormaps import angle_covered
from pipeline.lib.robot.errormaps import coverage as angle_coverage


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

"""The compensation service's logic (pipeline/commands/serve.py is only its transport): check a request,
solve it within a bounded budget, answer.

One worker thread owns the model. A request thread checks its request (`check`: numbers, joint
limits, reach; a RequestError naming the field), puts it on a queue and waits for its answer. The
worker, in a loop:
  1. takes what is queued (up to `max_batch`, a client's single requests before the items of batched
     calls, compensate_many's and a path's; when idle, it waits up to `batch_wait_ms` for as
     many as its last round took: a lone client never waits) and runs the controller path
     (two model evaluations) on all of them at once: on onnxruntime when given the exported graph
     (onnx_model.OnnxRealtime, the fast path), else in PyTorch (realtime.Realtime); each converged one
     is answered at once: converged only on a measured residual (an answer the controller path did
     not verify, whose residual is a prediction, goes on to lm);
  2. the others join the lm set, at most `lm_per_call` of one call's at a time and `max_batch` of every
     batched call's together (the rest wait for slots, so neither one call's many unreachable items nor
     many such calls at once can crowd out the others' requests), solved by `lm` from the controller path's answer where it predicted one within
     tol_mm (lm measures it there: one iteration), else from their start (solvers.lm_step, the residual
     then measured on the model; on the exported graph when the controller path runs there and lm
     steps with the DH branch's Jacobian, OnnxRealtime.lm_step, an iteration 2.5x cheaper than in
     PyTorch at batch 1): one iteration for the whole set per loop, so requests arriving
     meanwhile wait for one iteration, never for another request's solve. A request leaves the set
     converged (within tol_mm), stalled (its residual above `unreachable_mm` and not cut by
     `stall_ratio` in `stall_iter` iterations: the target cannot be reached), or at its budget
     (`max_iter` iterations or `budget_ms` from when it joined the lm set), or when its call's budget
     is spent (`call_budget_ms` from the call's start: compensate_many queues no more items then, and
     answers those not solved with an error in their place).
Left above `unreachable_mm`, a request is a RequestError "unreachable"; within it, an answer with
converged False. An answer in another configuration than the joints it was solved from (a shoulder, elbow
or wrist flipped, a joint turned over 180°: waypoints.another_configuration) is a RequestError too: a
client drives answers as moves. A pose (`compensate_pose`: an orientation too) skips the controller path (its graphs
solve positions) and joins a lane of its own (`Lane`): lm's six equations in PyTorch (solvers.residual),
one iteration a loop beside the positions' lane, under the same budgets. `compensate_path` queues a path's samples one at a time, each from the answer before
(lib/runtime/pathsolve.py), all under one call budget, and refuses the path as the path command does.
"""
import itertools
import math
import queue
import reprlib
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass, field, fields

import numpy as np
import pandas as pd
import torch
from scipy.spatial.transform import Rotation

from pipeline.lib.learning.model import PhysicsOnly
from pipeline.lib.project.columns import JCOMP_DEG
from pipeline.lib.robot.kinematics import DTYPE
from pipeline.lib.runtime.paths import ROTVEC_MAX_RAD, n_samples, resample, rotations_at, segments
from pipeline.lib.runtime.pathsolve import (SOLVED, beyond_reach, deviation, model_position, refusal,
                                            Timing, schedule)
from pipeline.lib.runtime.realtime import Realtime, answers
from pipeline.lib.runtime.solvers import LAM0, lm_jacobian, lm_step, orientation_angle, pose_weight, residual
from pipeline.lib.runtime.waypoints import METRES_MM, another_configuration


class RequestError(ValueError):
    """A bad or unreachable request; the message names the field."""


def shown() -> reprlib.Repr:
    """A repr that stops 3 lists deep and 6 items long (a request may nest thousands of lists)."""
    r = reprlib.Repr()
    r.maxlevel, r.maxlist, r.maxtuple, r.maxdict = 3, 6, 6, 3
    r.maxstring = r.maxlong = r.maxother = 40
    return r


SHOWN = shown()


@dataclass(frozen=True)
class Malformed:
    """A request's scalar its XML-RPC type does not read (`<double>abc</double>`): kept as this, so the
    field it was sent as is named (commands/serve.py's Unmarshaller), not the whole call refused."""
    tag: str
    text: str

    def __repr__(self) -> str:
        return f"<{self.tag}>{self.text}</{self.tag}>"


def describe(v) -> str:
    """A value's kind and its repr, cut to 40 characters (what a message may echo of it)."""
    kinds = {str: "a string", dict: "a struct", bool: "a boolean", list: "a list", tuple: "a list",
             int: "a number", float: "a number", type(None): "nil", Malformed: "a malformed value"}
    kind = kinds.get(type(v), type(v).__name__)
    text = SHOWN.repr(v)
    return f"{kind} ({text if len(text) <= 40 else text[:37] + '...'})"


def number(v, field: str) -> float:
    """v as a finite float, or a RequestError naming the field."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise RequestError(f"{field}: expected a number, got {describe(v)}")
    try:
        f = float(v)
    except OverflowError:                                  # an integer beyond any float
        f = math.inf
    if not math.isfinite(f):
        raise RequestError(f"{field}: not a finite number ({f})")
    return f


def positive(value, field: str) -> float:
    """value as a finite number > 0, or a RequestError naming the field."""
    f = number(value, field)
    if not f > 0:
        raise RequestError(f"{field}: expected a number > 0, got {value}")
    return f


def numbers(value, field: str, n: int) -> np.ndarray:
    """value as n finite floats, or a RequestError naming the field."""
    if not isinstance(value, (list, tuple)):
        raise RequestError(f"{field}: expected a list of {n} numbers, got {describe(value)}")
    if len(value) != n:
        raise RequestError(f"{field}: expected {n} numbers, got {len(value)}")
    return np.array([number(v, f"{field}[{i}]") for i, v in enumerate(value)])


@dataclass(eq=False)
class Job:
    q: np.ndarray                  # (6,) rad, the start
    target: np.ndarray             # (3,) mm
    where: str                     # the field prefix of its messages ("" or "requests[3].")
    call: object = None            # its call (compensate_many's items share one); None: a call of its own
    call_deadline: float = math.inf   # time.monotonic() at which its call's budget ends
    rot: np.ndarray | None = None  # (9,) a pose's flange orientation (row-major, base frame); None: a position
    rot_field: str = "target_rotvec"   # the request's field that gave rot (compensate_path's: rotvecs)
    start: str = ""                # where q came from, when not the request's q_rad (a path's previous sample)
    future: Future = field(default_factory=Future)
    deadline: float = 0.0          # time.monotonic() at which its budget ends (set when it joins lm)
    err0: float = math.inf         # |r| at seed, mm (the controller path's; inf: not measured there)
    seed: np.ndarray | None = None  # (6,) rad where lm starts: q, or the controller path's predicted answer
    iters: int = 0
    history: list = field(default_factory=list)   # |r| (mm) after each lm iteration, the start first


@dataclass
class LMSet:
    """The lm set's state, A rows: numpy arrays on the graph (r unused: None), else torch tensors."""
    q: object                      # (A, 6) rad
    r: object                      # (A, 3) mm, the residual at q
    err: object                    # (A,) mm, |r|
    lam: object                    # (A,) lm's damping
    target: object                 # (A, 3) mm; a pose's (A, 12): and the flange's orientation (solvers.residual)

    def _map(self, f) -> "LMSet":
        return LMSet(*(None if getattr(self, k.name) is None else f(k.name) for k in fields(self)))

    def rows(self, keep: list[int]) -> "LMSet":
        return self._map(lambda k: getattr(self, k)[keep])

    def join(self, other: "LMSet") -> "LMSet":
        cat = torch.cat if isinstance(self.q, torch.Tensor) else np.concatenate
        return self._map(lambda k: cat([getattr(self, k), getattr(other, k)]))


@dataclass(eq=False)
class Lane:
    """Jobs lm solves together, one iteration a worker loop: positions (w None: 3 equations, on the graph
    where there is one) or poses (w, solvers.pose_weight: 6 equations, in PyTorch)."""
    w: float | None
    jac: object                                           # solvers.lm_jacobian for this lane
    active: list = field(default_factory=list)            # its jobs, and their state (A rows)
    state: LMSet | None = None


class Service:
    """The model behind one worker thread; its methods are the service's (`compensate`, ...).

    model, workspace (lib/workspace.Workspace), limits_deg (6, 2), reach_mm (compensation.reach_mm),
    tol_mm and jacobian_of (the `compensate:` section), and the limits of the `serve:` section. controller:
    the controller path to run (onnx_model.OnnxRealtime on the same model, limits, tol_mm and workspace);
    None: realtime.Realtime on the model, compiled when `compile`. lm runs on the controller's graph when
    it is given and jacobian_of is physics (the graph's steps), else on the PyTorch model. compensate_path:
    at most max_path_samples samples, refused as the path command refuses (max_deviation_mm, the joint
    speed limits joint_speed_deg_s (6,); a string: why they are unknown), timed as the path command times it
    (path_timing: path.accel_mm_s2, path.corner_mm and the robot's pathsolve.cycle_s; a call gives the speed).
    frame_rot (3, 3): the served
    frame's rotation in the flange (the probe's, or a TCP's) for compensate_pose, None where the model was
    calibrated without orientation (compensate_pose refused); tol_arcsec its orientation's tolerance."""

    def __init__(self, model, workspace, limits_deg, reach_mm: float, *, tol_mm: float, jacobian_of: str,
                 unreachable_mm: float, max_iter: int, budget_ms: float, stall_iter: int, stall_ratio: float,
                 max_batch: int, batch_wait_ms: float, max_items: int, call_budget_ms: float, lm_per_call: int,
                 compile: bool, controller=None, max_path_samples: int = 1000, max_deviation_mm: float = 0.5,
                 path_timing: tuple, joint_speed_deg_s=None, frame_rot=None, tol_arcsec: float = 1.0):
        self.model, self.workspace, self.reach = model, workspace, float(reach_mm)
        self.limits_deg = np.asarray(limits_deg, float)
        self.limits = torch.as_tensor(np.radians(self.limits_deg), dtype=DTYPE)
        self.tol, self.unreachable = float(tol_mm), float(unreachable_mm)
        self.max_iter, self.budget = int(max_iter), float(budget_ms) / 1000
        self.stall_iter, self.stall_ratio = int(stall_iter), float(stall_ratio)
        self.max_batch, self.batch_wait = int(max_batch), float(batch_wait_ms) / 1000
        self.max_items, self.call_budget_ms, self.lm_per_call = int(max_items), float(call_budget_ms), int(lm_per_call)
        self.max_path_samples, self.max_deviation = int(max_path_samples), float(max_deviation_mm)
        self.joint_speeds, self.timing = joint_speed_deg_s, tuple(map(float, path_timing))   # compensate_path's
        self.position = model_position(PhysicsOnly(model))     # the path check's kinematics: no network, any thread
        self.realtime = controller if controller is not None else Realtime(
            model, np.radians(self.limits_deg), self.tol, workspace=workspace, compile=compile)
        self.graph = controller if controller is not None and jacobian_of == "physics" else None
        self.frame_rot = None if frame_rot is None else np.asarray(frame_rot, float)
        self.chain = model.physics.geometry()                  # whose configurations an answer keeps
        w = pose_weight({"tol_mm": self.tol, "tol_arcsec": tol_arcsec})
        self.lanes = {"position": Lane(None, lm_jacobian(model, jacobian_of)),
                      "pose": Lane(w, lm_jacobian(model, jacobian_of, w))}
        self.queue: queue.PriorityQueue = queue.PriorityQueue()   # (0: a call of its own, 1: a batch's item; seq, job)
        self.seq = itertools.count()                      # FIFO within a priority
        self.waiting: list[Job] = []                      # unconverged, waiting for a slot of their call's
        self.in_lm: dict[int, int] = {}                   # id(call): its jobs in the lm set
        self.last_round = 0                               # requests in the worker's last round
        self.closed = threading.Event()
        self.worker = threading.Thread(target=self._run, name="compensation worker", daemon=True)
        self.worker.start()

    def close(self) -> None:
        """Stop the worker; requests still waiting get a RequestError."""
        self.closed.set()
        self.worker.join()
        for job in self.active + self.waiting + [self.queue.get_nowait()[2] for _ in range(self.queue.qsize())]:
            job.future.set_exception(RequestError(f"{job.where}target_mm: the service stopped"))

    # the service's methods
    def check(self, q_rad, target_mm, where: str = "") -> tuple[np.ndarray, np.ndarray]:
        """q_rad (6 numbers within the joint limits) and target_mm (3 numbers within reach) as arrays,
        or a RequestError naming the field (prefixed `where`)."""
        q = self.joints(q_rad, where)
        return q, self.within_reach(numbers(target_mm, where + "target_mm", 3), where + "target_mm")

    def within_reach(self, point: np.ndarray, field: str) -> np.ndarray:
        """point (3,) mm, or a RequestError naming `field` where it lies beyond the arm's reach."""
        dist = float(np.linalg.norm(point))
        if dist > self.reach:
            raise RequestError(f"{field}: unreachable ({dist:.1f} mm from the base, beyond the arm's "
                               f"reach of {self.reach:.1f} mm)")
        return point

    def joints(self, q_rad, where: str = "") -> np.ndarray:
        """q_rad as 6 numbers within the joint limits, or a RequestError naming the field."""
        q = numbers(q_rad, where + "q_rad", 6)
        lo, hi = self.limits_deg[:, 0], self.limits_deg[:, 1]
        beyond = np.flatnonzero((np.degrees(q) < lo) | (np.degrees(q) > hi))
        if len(beyond):
            i = int(beyond[0])
            a, (lo, hi) = np.degrees(q[i]), self.limits_deg[i]
            raise RequestError(f"{where}q_rad[{i}]: {a:.1f}° ({q[i]:.3f} rad) beyond the joint limits "
                               f"[{lo:g}, {hi:g}]° ([{np.radians(lo):.3f}, {np.radians(hi):.3f}] rad)")
        return q

    @property
    def active(self) -> list[Job]:
        """Every job in lm now, both lanes."""
        return [j for lane in self.lanes.values() for j in lane.active]

    def submit(self, q: np.ndarray, target: np.ndarray, where: str = "", call=None,
               call_deadline: float = math.inf, rot: np.ndarray | None = None,
               rot_field: str = "target_rotvec", start: str = "") -> Future:
        """Queue a checked request for the worker (rot (3, 3): a pose's flange orientation; start: where q came
        from, when not the request's q_rad); its future holds the answer or a RequestError."""
        job = Job(q, target, where, call, call_deadline, None if rot is None else np.asarray(rot, float).ravel(),
                  rot_field, start)
        if self.closed.is_set():
            raise RequestError(f"{where}target_mm: the service stopped")
        self.queue.put((0 if call is None else 1, next(self.seq), job))   # a client's one request first
        return job.future

    def compensate(self, q_rad, target_mm) -> dict:
        """{q_rad, residual_mm, converged, in_workspace}, or a RequestError."""
        return self.submit(*self.check(q_rad, target_mm)).result()

    def compensate_pose(self, q_rad, target_mm, target_rotvec) -> dict:
        """compensate's struct and orientation_residual_arcsec, for a target orientation too: target_rotvec (3
        numbers, rad, base frame) the served frame's (the probe's, with --tcp the TCP's) rotation vector.
        Six equations, solved by lm in PyTorch (not on a controller graph), within the same
        budgets; a RequestError names the field."""
        self.orientation_served("target_rotvec", "call compensate with the position")
        q, target = self.check(q_rad, target_mm)
        return self.submit(q, target, rot=self.flange_target(target_rotvec, "target_rotvec")).result()

    def orientation_served(self, field: str, instead: str) -> None:
        """A RequestError naming field where the model was calibrated without the probe's orientation."""
        if self.frame_rot is None:
            raise RequestError(f"{field}: the model was calibrated without the probe's orientation, so an "
                               f"orientation cannot be compensated; {instead}")

    def flange_target(self, rotvec, field: str) -> np.ndarray:
        """The flange's orientation (3, 3), base frame, for the served frame's rotation vector rotvec (3 numbers,
        rad, base frame), checked: a RequestError names field."""
        rv = numbers(rotvec, field, 3)
        if np.linalg.norm(rv) > ROTVEC_MAX_RAD:
            raise RequestError(f"{field}: |{np.linalg.norm(rv):.3f}| rad, more than π: a rotation vector "
                               "in radians (degrees sent?)")
        return Rotation.from_rotvec(rv).as_matrix() @ self.frame_rot.T

    def compensate_list(self, q_rad, target_mm) -> list:
        """compensate's answer as 9 floats: q1..q6 rad, residual_mm, converged, in_workspace (1.0 / 0.0)."""
        r = self.compensate(q_rad, target_mm)
        return r["q_rad"] + [r["residual_mm"], float(r["converged"]), float(r["in_workspace"])]

    def compensate_many(self, requests) -> list:
        """Each [q_rad, target_mm] answered in its place: compensate's struct, or {"error": message} for a
        bad, unreachable or unsolved item. At most `max_items`; queued `max_batch` at a time, so other
        clients' requests are taken between them; within `call_budget_ms` from now: the items not solved by
        then are an error naming it."""
        if not isinstance(requests, (list, tuple)):
            raise RequestError(f"requests: expected a list of [q_rad, target_mm], got {describe(requests)}")
        if len(requests) > self.max_items:
            raise RequestError(f"requests: {len(requests)} items, more than the limit of {self.max_items} "
                               f"(serve.max_items): split the batch")
        out, call = [], object()
        deadline = time.monotonic() + self.call_budget_ms / 1000
        for start in range(0, len(requests), self.max_batch):
            chunk, spent = [], time.monotonic() >= deadline
            for i, item in enumerate(requests[start:start + self.max_batch], start):
                try:
                    if not isinstance(item, (list, tuple)) or len(item) != 2:
                        raise RequestError(f"requests[{i}]: expected [q_rad, target_mm], got {describe(item)}")
                    q, target = self.check(*item, where=f"requests[{i}].")
                    chunk.append(self._unsolved(f"requests[{i}].") if spent else
                                 self.submit(q, target, f"requests[{i}].", call, deadline))
                except RequestError as e:
                    chunk.append(str(e))
            for f in chunk:
                try:
                    out.append({"error": f} if isinstance(f, str) else f.result())
                except RequestError as e:
                    out.append({"error": str(e)})
        return out

    def compensate_path(self, q_rad, points_mm, moves, spacing_mm, speed_mm_s, rotvecs=()) -> dict:
        """A TCP path (points_mm, moves as the path command's file: movel, movep, via + movec; [] every
        move movel) resampled at most spacing_mm apart, each sample solved from the previous one's answer, the
        first from q_rad, in order, within one call budget (`call_budget_ms`); refused as the path command
        refuses (lib/pathsolve.refusal, and a sample in another configuration than the joints it was solved
        from, as every answer: `_settle`; outside the trained workspace: flagged, not refused), else
        {q_rad, target_mm, arc_mm, t_s (servoj's times at speed_mm_s), residual_mm, in_workspace: per sample,
        all_in_workspace}. rotvecs, one per point (as compensate_pose's target_rotvec; [] or left out: none): the
        orientation held too, slerped between the points (paths.rotations_at), six equations a sample in the
        pose lane; the answer then has orientation_residual_arcsec per sample. A RequestError names the field."""
        deadline = time.monotonic() + self.call_budget_ms / 1000
        if not isinstance(points_mm, (list, tuple)):
            raise RequestError(f"points_mm: expected a list of [x, y, z], got {describe(points_mm)}")
        if not 2 <= len(points_mm) <= self.max_path_samples:
            raise RequestError(f"points_mm: {len(points_mm)} points: a path needs 2 to {self.max_path_samples} "
                               "(serve.max_path_samples)")
        points = np.array([self.within_reach(numbers(p, f"points_mm[{i}]", 3), f"points_mm[{i}]")   # before its
                           for i, p in enumerate(points_mm)])                                    # length counts samples
        if not isinstance(moves, (list, tuple)) or len(moves) not in (0, len(points)):
            raise RequestError(f"moves: expected a list of {len(points)} strings (or [], every move movel), got "
                               f"{describe(moves)}")
        for i, m in enumerate(moves):
            if not isinstance(m, str):
                raise RequestError(f"moves[{i}]: expected a string, got {describe(m)}")
        spacing, speed = positive(spacing_mm, "spacing_mm"), positive(speed_mm_s, "speed_mm_s")
        if not isinstance(rotvecs, (list, tuple)) or len(rotvecs) not in (0, len(points)):
            raise RequestError(f"rotvecs: expected a list of {len(points)} rotation vectors [rx, ry, rz] (rad), one "
                               f"per point (or [], no orientation), got {describe(rotvecs)}")
        if len(rotvecs):
            self.orientation_served("rotvecs", "leave them out to compensate the positions")
        rots = np.array([self.flange_target(r, f"rotvecs[{i}]") for i, r in enumerate(rotvecs)])   # (n, 3, 3)
        q = self.joints(q_rad)
        if isinstance(self.joint_speeds, str):
            raise RequestError(f"speed_mm_s: {self.joint_speeds}")
        try:
            segs = segments(points, list(moves) or [""] + ["movel"] * (len(points) - 1),
                            lambda i: f"moves[{i}] (points_mm[{i}])")
        except ValueError as e:
            raise RequestError(str(e)) from None
        n = n_samples(segs, spacing)
        if n > self.max_path_samples:
            raise RequestError(f"spacing_mm: a {sum(s.length for s in segs):.1f} mm path at {spacing:g} mm is {n} "
                               f"samples, more than the limit of {self.max_path_samples} (serve.max_path_samples): "
                               "a larger spacing, or split the path")
        targets, arc = resample(segs, spacing)
        try:
            timing = Timing(speed, *self.timing)
            timed = schedule(targets, arc, timing)
        except ValueError as e:
            raise RequestError(f"speed_mm_s: {e}") from None
        flange = rotations_at(segs, rots, arc) if len(rots) else [None] * len(arc)   # (m, 3, 3): per sample
        far = beyond_reach(targets, arc, self.reach)
        if far:
            raise RequestError(f"points_mm: {far}")
        rows, call = [], object()
        for k, (x, a) in enumerate(zip(targets, arc)):
            where = f"points_mm: sample {k + 1} (arc {a:.1f} mm), "
            if time.monotonic() >= deadline:
                raise RequestError(self._unsolved(where))
            r = self.submit(q, x, where, call, deadline, rot=flange[k], rot_field="rotvecs",
                            start=f"sample {k}'s answer" if k else "").result()
            q = np.array(r["q_rad"])
            rows.append([a, *x, *np.degrees(q), r["residual_mm"], 0, r["converged"],
                         r.get("orientation_residual_arcsec", np.nan), r["in_workspace"]])
            if not r["converged"]:
                break
        table = pd.DataFrame(rows, columns=SOLVED + ["in_workspace"])       # the path command's, and in_workspace
        qd = table[JCOMP_DEG].to_numpy()
        why = refusal(table, n, self.limits_deg, self.tol, deviation(self.position, qd, segs, table.arc_mm.to_numpy()), self.max_deviation,
                      timed.peak_mm_s, self.joint_speeds)
        if why:
            raise RequestError(f"points_mm: {why}")
        return {"q_rad": np.radians(qd).tolist(), "target_mm": targets.tolist(), "arc_mm": arc.tolist(),
                "t_s": timed.t_s.tolist(),
                "residual_mm": table.residual_mm.tolist(), "in_workspace": table.in_workspace.astype(bool).tolist(),
                "all_in_workspace": bool(table.in_workspace.all()),
                **({"orientation_residual_arcsec": table.orientation_residual_arcsec.tolist()} if len(rots) else {})}

    def _unsolved(self, where: str, residual: str = "") -> str:
        return (f"{where}target_mm: not solved{residual}: the call's budget of {self.call_budget_ms:g} ms "
                f"(serve.call_budget_ms) was spent")

    # the worker
    def _run(self) -> None:
        while not self.closed.is_set():
            jobs = self._take(wait=not self.active)
            try:
                if jobs:
                    self._chord(jobs)
                for lane in self.lanes.values():
                    if lane.active:
                        self._lm_iteration(lane)
            except Exception as e:                        # a bug: fail these requests, keep serving
                for job in jobs + self.active + self.waiting:
                    if not job.future.done():
                        job.future.set_exception(e)
                for lane in self.lanes.values():
                    lane.active, lane.state = [], None
                self.waiting, self.in_lm = [], {}

    def _take(self, wait: bool) -> list[Job]:
        """What is queued, up to max_batch, the calls of their own before the items of batched calls
        (compensate_many, a path's samples); wait (the worker is idle): block for the first, then wait up to
        batch_wait while fewer have come than the last round had (a lone client never waits)."""
        jobs = []
        if wait:
            try:
                jobs.append(self.queue.get(timeout=0.1)[2])  # wakes to see `closed`
            except queue.Empty:
                return jobs
        until = time.monotonic() + (self.batch_wait if wait else 0.0)
        while len(jobs) < self.max_batch:
            left = until - time.monotonic() if len(jobs) < self.last_round else 0.0
            try:
                jobs.append((self.queue.get(timeout=left) if left > 0 else self.queue.get_nowait())[2])
            except queue.Empty:
                break
        if jobs:
            self.last_round = len(jobs)
        return jobs

    def _chord(self, jobs: list[Job]) -> None:
        """The controller path for every job at once; the converged (on a measured residual) answered, the
        others on to lm (`_admit`): from the answer where its predicted residual is within tol, else from their
        start. Jobs whose call's budget is spent: answered so."""
        start = time.monotonic()
        for job in [j for j in jobs if start >= j.call_deadline]:
            job.future.set_exception(RequestError(self._unsolved(job.where)))
        jobs = [j for j in jobs if start < j.call_deadline]
        self.waiting += [j for j in jobs if j.rot is not None]   # a pose: lm from its start (the graphs: positions)
        jobs = [j for j in jobs if j.rot is None]
        if not jobs:
            self._admit()
            return
        q0, target = np.array([j.q for j in jobs]), np.array([j.target for j in jobs])
        if self.graph is not None:
            out = self.graph.solve(q0, target)             # q1, q2, |r0|, |r1|
            results = answers(*out, self.tol, self.workspace, self.graph.limits)
            for job, e in zip(jobs, out[2].tolist()):
                job.err0 = e
        else:
            results = self.realtime.batch(q0, target)
        for job, r in zip(jobs, results):
            if r.converged and r.verified:
                self._settle(job, self._answer(r.q, r.residual_mm, True, r.in_workspace), "target_mm")
                continue
            if r.converged:                                # a predicted residual: lm measures it there
                job.seed, job.err0 = r.q, math.inf
            self.waiting.append(job)
        self._admit()

    def _admit(self) -> None:
        """Move waiting jobs into the lm set, in order, as their calls have slots (lm_per_call each, max_batch
        for every batched call's together: however many such calls, an lm iteration's rows stay bounded); those
        whose call's budget is spent are answered so."""
        now, admit, wait = time.monotonic(), [], []
        batched = sum(self.in_lm.values())
        for job in self.waiting:
            n = self.in_lm.get(id(job.call), 0)
            if now >= job.call_deadline:
                job.future.set_exception(RequestError(self._unsolved(job.where)))
            elif job.call is None or (n < self.lm_per_call and batched < self.max_batch):
                if job.call is not None:
                    self.in_lm[id(job.call)] = n + 1
                    batched += 1
                job.deadline = now + self.budget
                admit.append(job)
            else:
                wait.append(job)
        self.waiting = wait
        for lane, jobs in ((self.lanes["position"], [j for j in admit if j.rot is None]),
                           (self.lanes["pose"], [j for j in admit if j.rot is not None])):
            if jobs:
                self._join(lane, jobs)

    def _join(self, lane: Lane, admit: list[Job]) -> None:
        """Jobs into a lane's lm set, each from its seed (its start where it has none)."""
        q0 = np.array([j.q if j.seed is None else j.seed for j in admit])
        target = np.array([j.target for j in admit])
        if lane.w is None and self.graph is not None:
            err0 = np.array([j.err0 for j in admit])
            seeded = ~np.isfinite(err0)                    # |r| at a predicted answer: measured by one run
            if seeded.any():
                err0[seeded] = self.graph.solve(q0[seeded], target[seeded])[2]
            new = LMSet(q0, None, err0, np.full(len(admit), LAM0), target)
        else:
            if lane.w is not None:                        # (A, 12): the position and the flange's orientation
                target = np.hstack([target, np.array([j.rot for j in admit])])
            q, t = torch.tensor(q0, dtype=DTYPE), torch.tensor(target, dtype=DTYPE)
            with torch.no_grad():
                r = residual(self.model, q, t, lane.w)
            new = LMSet(q, r, r.norm(dim=1), torch.full((len(admit),), LAM0, dtype=DTYPE), t)
        for job, e in zip(admit, new.err.tolist()):
            job.history.append(e)
        lane.active += admit
        lane.state = new if lane.state is None else lane.state.join(new)
        self._finish(lane)

    def _lm_iteration(self, lane: Lane) -> None:
        s = lane.state
        if lane.w is None and self.graph is not None:
            s.q, s.err, s.lam = self.graph.lm_step(s.q, s.target, s.err, s.lam)
        else:
            s.q, s.r, s.err, s.lam = lm_step(self.model, lane.jac, s.q, s.r, s.err, s.lam, s.target, self.limits,
                                             w=lane.w)
        for job, e in zip(lane.active, s.err.tolist()):
            job.iters += 1
            job.history.append(e)
        self._finish(lane)

    def _finish(self, lane: Lane) -> None:
        """Answer the jobs of a lane's lm set that converged, stalled or spent their budget or their call's;
        keep the rest, and let waiting jobs into the slots freed."""
        q = lane.state.q
        now, keep = time.monotonic(), []
        for i, job in enumerate(lane.active):
            e, h = job.history[-1], job.history
            stalled = (e > self.unreachable and len(h) > self.stall_iter
                       and e > self.stall_ratio * h[-1 - self.stall_iter])
            spent = job.iters >= self.max_iter or now >= job.deadline or now >= job.call_deadline
            if not (e < self.tol or stalled or spent):
                keep.append(i)
                continue
            if job.call is not None:
                self.in_lm[id(job.call)] -= 1
                if not self.in_lm[id(job.call)]:
                    del self.in_lm[id(job.call)]
            if e >= self.tol and e > self.unreachable and not stalled and now >= job.call_deadline:
                job.future.set_exception(RequestError(self._unsolved(
                    job.where, f" (residual {e:.1f} mm after {job.iters} iterations)")))
                continue
            if lane.w is None:
                field, said, extra = "target_mm", f"{e:.1f} mm", {}
            else:                                         # a pose: the position's residual and the orientation's
                r = lane.state.r[i].numpy()
                qi = torch.as_tensor(np.asarray(q[i], float)[None], dtype=DTYPE)
                angle = orientation_angle(self.model.physics.geometry(), qi,
                                          torch.as_tensor(np.r_[job.target, job.rot][None], dtype=DTYPE))
                arcsec = float(np.degrees(angle[0].item()) * 3600)   # the whole angle (|r[3:]| / w is sin θ: 0 at 180°)
                field, said = f"target_mm, {job.rot_field}", f"{np.linalg.norm(r[:3]):.1f} mm and {arcsec:.0f} arcsec"
                extra = {"orientation_residual_arcsec": arcsec}
                if arcsec > 324000.0:                           # past 90°: a flange turned half round
                    job.future.set_exception(RequestError(
                        f"{job.where}{field}: unreachable from q_rad (the flange's orientation {arcsec:.0f} arcsec, "
                        f"{arcsec / 3600:.1f}°, off after compensation: beyond 90°, lm turns it no nearer; start "
                        "from joints nearer the target's orientation)"))
                    continue
            if e < self.tol or e <= self.unreachable:
                q_rad = (q[i].numpy() if isinstance(q, torch.Tensor) else q[i]).astype(float)   # a copy
                inside = bool(self.workspace(np.degrees(q_rad)[None])[1][0])
                answer = self._answer(q_rad, e, e < self.tol, inside)
                if extra:
                    answer["residual_mm"] = float(np.linalg.norm(r[:3]))
                self._settle(job, {**answer, **extra}, field)
                continue
            why = (f"no progress in {self.stall_iter} iterations" if stalled else
                   f"the budget: {job.iters} iterations, {1000 * (now - job.deadline + self.budget):.0f} ms")
            units = (" target_mm is in millimetres: a target this close to the base looks like metres."
                     if np.linalg.norm(job.target) < METRES_MM else "")
            job.future.set_exception(RequestError(
                f"{job.where}{field}: unreachable (residual {said} after compensation, tolerance "
                f"{self.tol:g} mm; {why}).{units}"))
        if len(keep) < len(lane.active):
            lane.active = [lane.active[i] for i in keep]
            lane.state = lane.state.rows(keep) if keep else None
            if self.waiting:
                self._admit()

    def _settle(self, job: Job, answer: dict, field: str) -> None:
        """job's answer, or a RequestError where it left the configuration of the joints it was solved from
        (waypoints.another_configuration: a client would drive it as a move)."""
        why = another_configuration(np.degrees(job.q), np.degrees(answer["q_rad"]), self.chain,
                                    orientation=job.rot is not None, than=job.start or "the given joints' (q_rad)",
                                    advice="a branch flip: a finer spacing_mm, or another path" if job.start
                                    else "give joints nearer the target")[0]
        if why is None:
            job.future.set_result(answer)
        else:
            job.future.set_exception(RequestError(f"{job.where}{field}: reached only in {why}"))

    @staticmethod
    def _answer(q_rad, residual: float, converged: bool, in_workspace: bool) -> dict:
        return {"q_rad": [float(v) for v in q_rad], "residual_mm": float(residual), "converged": bool(converged),
                "in_workspace": bool(in_workspace)}

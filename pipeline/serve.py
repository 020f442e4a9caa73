"""The compensation service: the trained model over XML-RPC, for a robot program to call.

    python -m pipeline.serve [--port N] [--host H]     (defaults: the `serve:` section of params.yaml)

XML-RPC at http://HOST:PORT/RPC2 (only that path; default 127.0.0.1:50000):

    compensate(q_rad, target_mm)           6 joint angles (rad) to start from, 3 target coordinates (mm,
                                           the model's base frame: that of reports/frame.json) ->
                                           {"q_rad": [6 floats], "residual_mm": float,
                                            "converged": bool, "in_workspace": bool}
    compensate_many([[q_rad, target_mm], ...])   a list of those structs, in order
    compensate_list(q_rad, target_mm)      the same answer as one flat list of 9 floats (for URScript,
                                           see below): [q1..q6 rad, residual_mm, converged 1.0/0.0,
                                           in_workspace 1.0/0.0]
    system.listMethods, system.methodHelp, system.methodSignature

Each pose goes through the controller path (lib/realtime.py: two model
evaluations, ~7 ms here eager, ~2.5 ms with `serve.compile` / `--compile`). When that does not converge within
`compensate.tol_mm` (a start far from the answer), the batched solver
(lib/solvers.py, `lm`, up to `compensate.max_iter` iterations) solves it
again from q_rad, and the residual returned is then measured on the model.
The answer always respects the joint limits (`robot` section). `in_workspace`:
the answer lies within the trained workspace (lib/workspace.py).

Bad requests get an XML-RPC Fault whose message names the field and the
problem (`q_rad: expected 6 numbers, got 5`, `target_mm[1]: not a finite number
(nan)`, `q_rad[2]: 400.0° (6.981 rad) beyond the joint limits [-360, 360]°`,
`requests[3].q_rad: ...` inside compensate_many); the server keeps serving.
A target is *unreachable* (a Fault, not an answer) when
  - it lies farther from the base than the arm can reach: the sum of the
    model's link lengths |a| + |d|, its tool offset and base shift (a generous
    bound: a target beyond it can be reached by no joint angles), or
  - after both solvers the residual still exceeds `serve.unreachable_mm`
    (the target needs angles beyond the joint limits, or lies outside the arm's workspace).
A target solved to a residual above `compensate.tol_mm` but within
`serve.unreachable_mm` is answered with converged False.

The model is shared by the server's threads (one per request) behind a lock:
requests are answered one at a time; clients may connect concurrently. It
refuses to start without the trained artifacts (`dvc repro` makes them).

The server listens on 127.0.0.1 only, unless told otherwise: to serve a robot
on the network, `python -m pipeline.serve --host 0.0.0.0` (or the PC's address
on the robot's network) and open the port in the PC's firewall.

URScript (the robot program), with the PC at 192.168.1.10:

    comp = rpc_factory("xmlrpc", "http://192.168.1.10:50000/RPC2")
    r = comp.compensate_list(get_actual_joint_positions(), [x_mm, y_mm, z_mm])
    if r[7] > 0.5:
      movej([r[0], r[1], r[2], r[3], r[4], r[5]])
    end

URScript sends its lists as arrays of doubles (get_actual_joint_positions()
is a list of 6 floats in rad), which is what both methods take. Its documented
variable types are bool, int, float, string, pose and list, and the one struct
its XML-RPC exchanges is a pose (members x, y, z, rx, ry, rz). So a robot
program reads `compensate_list`'s flat list, by index, on every
PolyScope version; the struct of `compensate` is for other clients (Python's
xmlrpc.client: r["q_rad"], r["converged"]) and for controllers whose URScript
reads structs. The targets are in the model's base frame (the DH base of
reports/frame.json), in mm; a UR controller's poses are in metres, and in a
base frame that may be turned about z from the DH base (the ipa-ur10 preset
measured 180°: `validate.commanded.rz_deg`), so convert before calling.
"""
import argparse
import inspect
import math
import socketserver
import threading
from pathlib import Path
from xmlrpc.client import Fault
from xmlrpc.server import SimpleXMLRPCRequestHandler, SimpleXMLRPCServer

import numpy as np
import torch

from .lib.artifacts import MODEL_WEIGHTS, WORKSPACE_JSON
from .lib.compensation import reach_mm
from .lib.config import for_stage, load_params, logger, read_json
from .lib.realtime import Realtime
from .lib.robots import load_robot
from .lib.solvers import compensate
from .lib.training import load_model
from .lib.workspace import Workspace

log = logger(__name__)
PATH = "/RPC2"
INVALID_PARAMS, NO_METHOD, INTERNAL = -32602, -32601, -32603       # the XML-RPC fault code convention


PARAMS = ("robot", "compensate", "serve")
REQUIRED = [MODEL_WEIGHTS, WORKSPACE_JSON]                # the trained artifacts it reads (the checkpoint
                                                          # carries its config and physics geometry)


def check_artifacts() -> None:
    missing = [str(p) for p in REQUIRED if not p.exists()]
    if missing:
        raise SystemExit(f"pipeline.serve: missing trained artifact(s) {', '.join(missing)} "
                         f"(in {Path.cwd()}); run `dvc repro` first")


class BadRequest(Fault):
    def __init__(self, message: str):
        super().__init__(INVALID_PARAMS, message)


def numbers(value, field: str, n: int) -> np.ndarray:
    """value as n finite floats, or a BadRequest naming the field."""
    if not isinstance(value, (list, tuple)):
        raise BadRequest(f"{field}: expected a list of {n} numbers, got {describe(value)}")
    if len(value) != n:
        raise BadRequest(f"{field}: expected {n} numbers, got {len(value)}")
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise BadRequest(f"{field}[{i}]: expected a number, got {describe(v)}")
        try:
            f = float(v)
        except OverflowError:                              # an integer beyond any float
            f = math.inf
        if not math.isfinite(f):
            raise BadRequest(f"{field}[{i}]: not a finite number ({f})")
    return np.array(value, float)


def describe(v) -> str:
    kinds = {str: "a string", dict: "a struct", bool: "a boolean", list: "a list", tuple: "a list",
             int: "a number", float: "a number", type(None): "nil"}
    text = repr(v)
    return f"{kinds.get(type(v), type(v).__name__)} ({text if len(text) <= 40 else text[:37] + '...'})"


class Compensator:
    """The model, its workspace and limits; its methods are the service's (`compensate`, ...)."""

    def __init__(self, params: dict):
        self.cfg, serve = params["compensate"], params["serve"]
        self.robot = load_robot(params["robot"])
        self.model = load_model(MODEL_WEIGHTS)
        self.limits_deg = np.asarray(self.robot.limits_deg, float)
        self.tol, self.unreachable = float(self.cfg["tol_mm"]), float(serve["unreachable_mm"])
        workspace = Workspace.from_dict(read_json(WORKSPACE_JSON))
        self.realtime = Realtime(self.model, np.radians(self.limits_deg), self.tol, workspace=workspace,
                                 compile=bool(serve["compile"]))
        self.reach = reach_mm(self.model.physics.geometry())
        self.lock = threading.Lock()                      # one model evaluation at a time

    def check(self, q_rad, target_mm, where: str = "") -> tuple[np.ndarray, np.ndarray]:
        q, target = numbers(q_rad, where + "q_rad", 6), numbers(target_mm, where + "target_mm", 3)
        beyond = np.flatnonzero(self.robot.check_joints(np.degrees(q)[None])[0])
        if len(beyond):
            i = int(beyond[0])
            a, (lo, hi) = np.degrees(q[i]), self.limits_deg[i]
            raise BadRequest(f"{where}q_rad[{i}]: {a:.1f}° ({q[i]:.3f} rad) beyond the joint limits "
                             f"[{lo:g}, {hi:g}]° ([{np.radians(lo):.3f}, {np.radians(hi):.3f}] rad)")
        dist = float(np.linalg.norm(target))
        if dist > self.reach:
            raise BadRequest(f"{where}target_mm: unreachable ({dist:.1f} mm from the base, beyond the arm's "
                             f"reach of {self.reach:.1f} mm)")
        return q, target

    def solve(self, q: np.ndarray, target: np.ndarray, where: str = "") -> dict:
        with self.lock:
            r = self.realtime(q, target)
            q_out, residual, converged = r.q, r.residual_mm, r.converged
            if not converged:                             # far start: the full solver, residual measured
                q_deg, pred, _, ok, _, _ = compensate(self.model, np.degrees(q)[None], target[None],
                                                      self.cfg, self.robot, "lm")
                q_out, residual, converged = np.radians(q_deg[0]), float(np.linalg.norm(pred[0] - target)), bool(ok[0])
                in_ws = bool(self.realtime.workspace(q_deg)[1][0])
            else:
                in_ws = bool(r.in_workspace)
        if not converged and residual > self.unreachable:
            raise BadRequest(f"{where}target_mm: unreachable (residual {residual:.1f} mm after compensation, "
                             f"tolerance {self.tol:g} mm)")
        return {"q_rad": [float(v) for v in q_out], "residual_mm": float(residual), "converged": bool(converged),
                "in_workspace": in_ws}

    # the XML-RPC methods
    def compensate(self, q_rad, target_mm):
        """compensate(q_rad [6], target_mm [3]) -> {q_rad, residual_mm, converged, in_workspace}."""
        return self.solve(*self.check(q_rad, target_mm))

    def compensate_list(self, q_rad, target_mm):
        """compensate_list(q_rad [6], target_mm [3]) -> [q1..q6 rad, residual_mm, converged, in_workspace]
        as 9 floats (1.0 / 0.0 for the flags): URScript reads lists, not structs."""
        r = self.compensate(q_rad, target_mm)
        return r["q_rad"] + [r["residual_mm"], float(r["converged"]), float(r["in_workspace"])]

    def compensate_many(self, requests):
        """compensate_many([[q_rad, target_mm], ...]) -> [{q_rad, residual_mm, converged, in_workspace}, ...]."""
        if not isinstance(requests, (list, tuple)):
            raise BadRequest(f"requests: expected a list of [q_rad, target_mm], got {describe(requests)}")
        checked = []
        for i, item in enumerate(requests):                # every item checked before any is solved
            if not isinstance(item, (list, tuple)) or len(item) != 2:
                raise BadRequest(f"requests[{i}]: expected [q_rad, target_mm], got {describe(item)}")
            checked.append(self.check(*item, where=f"requests[{i}]."))
        return [self.solve(q, t, where=f"requests[{i}].") for i, (q, t) in enumerate(checked)]


class Handler(SimpleXMLRPCRequestHandler):
    rpc_paths = (PATH,)                                   # any other path: 404


class Server(socketserver.ThreadingMixIn, SimpleXMLRPCServer):
    """SimpleXMLRPCServer, one thread per request; faults logged, never fatal."""
    daemon_threads = True
    request_queue_size = 64                               # listen backlog: socketserver's 5 drops concurrent connects

    def _dispatch(self, method, params):
        try:
            func = self.funcs.get(method)
            if func is None:
                raise Fault(NO_METHOD, f"unknown method {method!r}; methods: {', '.join(sorted(self.funcs))}")
            try:
                inspect.signature(func).bind(*params)
            except TypeError:
                names = ", ".join(inspect.signature(func).parameters)
                raise Fault(INVALID_PARAMS, f"{method}: expected {len(inspect.signature(func).parameters)} "
                                            f"argument(s) ({names}), got {len(params)}") from None
            return func(*params)
        except Fault as f:
            log.warning("%s: fault: %s", method, f.faultString)
            raise
        except Exception as e:                            # a bug, not a bad request: say so, keep serving
            log.exception("%s: internal error", method)
            raise Fault(INTERNAL, f"{method}: internal error ({type(e).__name__}: {e})") from None


def make_server(params: dict, host: str | None = None, port: int | None = None,
                compile: bool | None = None) -> Server:
    """The service on host:port (None: the `serve:` section; port 0: a free port, in server.server_address),
    not yet serving: call serve_forever()."""
    params = for_stage(params, PARAMS)
    cfg = params["serve"]
    if compile is not None:
        params = {**params, "serve": {**cfg, "compile": compile}}
    host, port = cfg["host"] if host is None else host, cfg["port"] if port is None else port
    check_artifacts()
    comp = Compensator(params)
    try:
        server = Server((host, port), requestHandler=Handler, allow_none=False, logRequests=False)
    except OSError as e:
        raise SystemExit(f"pipeline.serve: cannot listen on {host}:{port}: {e}") from None
    server.register_introspection_functions()
    for name in ("compensate", "compensate_many", "compensate_list"):
        server.register_function(getattr(comp, name), name)
    server.compensator = comp
    return server


def url(server: Server) -> str:
    host, port = server.server_address[:2]
    return f"http://{host}:{port}{PATH}"


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m pipeline.serve", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--port", type=int, default=None, help="TCP port (default: serve.port)")
    ap.add_argument("--host", default=None, help="address to listen on (default: serve.host; 0.0.0.0: every "
                                                 "interface, to serve a robot on the network)")
    ap.add_argument("--compile", action=argparse.BooleanOptionalAction, default=None,
                    help="torch.compile the controller path (default: serve.compile)")
    a = ap.parse_args(argv)
    server = make_server(load_params(), a.host, a.port, a.compile)
    log.info("serving %s: %s (torch %d threads)", url(server), ", ".join(server.system_listMethods()),
             torch.get_num_threads())
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        log.info("stopped")
    finally:
        server.server_close()


if __name__ == "__main__":
    main()

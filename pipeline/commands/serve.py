"""The compensation service: the trained model over XML-RPC, for a robot program to call.

    python -m pipeline.commands.serve [--port N] [--host H] [--no-onnx] [--compile] [--tcp NAME]   (defaults: the `serve:` section)

XML-RPC at http://HOST:PORT/RPC2 (only that path, only POST; default 127.0.0.1:50000):

    compensate(q_rad, target_mm)         6 joint angles (rad) to start from, 3 target coordinates (mm, the
                                         model's base frame: that of reports/frame.json) ->
                                         {"q_rad": [6 floats], "residual_mm": float, "converged": bool,
                                          "in_workspace": bool}
    compensate_pose(q_rad, target_mm, target_rotvec)   and the orientation: target_rotvec, 3 numbers, the
                                         rotation vector (rad, base frame) of the probe's frame (with --tcp,
                                         of the TCP's); six equations, solved by lm in PyTorch -> compensate's
                                         struct and "orientation_residual_arcsec"; refused for a model
                                         calibrated without orientation
    compensate_list(q_rad, target_mm)    the same answer as 9 floats, for URScript: [q1..q6 rad,
                                         residual_mm, converged 1.0/0.0, in_workspace 1.0/0.0]
    compensate_many([[q_rad, target_mm], ...])   at most serve.max_items; each item answered in its
                                         place: compensate's struct, or {"error": "requests[3].q_rad: ..."}
    compensate_path(q_rad, points_mm, moves, spacing_mm, speed_mm_s)   a TCP path (its waypoints, mm, and
                                         moves: movel, movep, via + movec; [] all movel) resampled at most
                                         spacing_mm apart, every sample solved from the one before, within
                                         serve.max_path_samples and serve.call_budget_ms -> {"q_rad": [[6]
                                         per sample], "target_mm", "arc_mm", "t_s", "residual_mm",
                                         "in_workspace": per sample, "all_in_workspace": bool}, or a Fault
                                         naming the field (a sample that must not be driven: points_mm);
                                         a 6th argument, rotvecs (one rotation vector per point, as
                                         target_rotvec), holds the orientation too, slerped between the
                                         points (and "orientation_residual_arcsec" per sample)
    system.listMethods, system.methodHelp, system.methodSignature

With --tcp NAME every target is that `robot.tcp` point's (lib/robot/tcp.py AtTcp: the marker's answer moved
along the probe's orientation), not the marker's; the controller path then runs on the export stage's
models/controller_tcp.onnx (controller_physics_tcp.onnx), fed that point, and a model calibrated
without orientation is refused.

What a request costs and when it is answered, refused or unreachable: lib/runtime/service.py (the logic: a
worker thread owning the model batches concurrent requests; each has a budget, serve.max_iter and
serve.budget_ms, a compensate_many call one in all, serve.call_budget_ms, and at most serve.lm_per_call
of its items in lm at a time, serve.max_batch of every batched call's together; a client's single
requests taken before batched items). The controller path runs on onnxruntime, from the export stage's models/controller.onnx
(serve.onnx; checked against the PyTorch model at start-up), else in PyTorch. A bad or unreachable request gets a Fault (code -32602) naming the field; the
server keeps serving. This module is the transport: the HTTP limits (serve.max_body_bytes, on the body
as sent and as gzip-decoded: 413; serve.timeout_s: a request not fully sent that long after it began, or
after the previous answer on a keep-alive connection, is closed, and so is an answer not taken that
long; serve.max_connections open at once, beyond: 503 at once, no thread; malformed HTTP, a body that
is not an XML-RPC call, or has a DOCTYPE or entity declaration (refused before any expansion): 400;
other methods than POST: 405; HTTP/1.1 keep-alive), messages and log lines that echo a request (an
unknown method, an internal error, a connection's error: one line) cut to serve.echo_chars, a bad
request's fault (the service's own words, each value it echoes cut to 40 characters) to MESSAGE_CHARS,
the faults' log lines to FAULT_LINES at once and FAULT_LINES_PER_S after (the others counted), and loading the artifacts and params. It listens on 127.0.0.1 unless told otherwise (--host
0.0.0.0 to serve a robot on the network; XML-RPC has no authentication). docs/robot-cell.md: the
protocol and a URScript example.
"""
import argparse
import inspect
import math
import socket
import socketserver
import sys
import threading
import time
import xmlrpc.client
import zlib
from pathlib import Path
from xml.parsers import expat
from xmlrpc.client import Fault
from xmlrpc.server import SimpleXMLRPCRequestHandler, SimpleXMLRPCServer

import numpy as np
import torch

from pipeline.lib.learning.checkpoint import load_model
from pipeline.lib.learning.model import served
from pipeline.lib.learning.onnx_model import OnnxRealtime, deviation
from pipeline.lib.learning.workspace import Workspace
from pipeline.lib.project.artifacts import (CONTROLLER_ONNX, CONTROLLER_PHYSICS_ONNX,
                                            CONTROLLER_PHYSICS_TCP_ONNX, CONTROLLER_TCP_ONNX, HERE, MODEL_WEIGHTS,
                                            PARAMS_FILE, WORKSPACE_JSON, require)
from pipeline.lib.project.cli import add_project
from pipeline.lib.project.config import ParamsError, for_stage, load_params, logger, read_json
from pipeline.lib.robot.geometry import theory_geometry
from pipeline.lib.robot.kinematics import TOOL_ROT, tool_rotation
from pipeline.lib.robot.robots import load_robot
from pipeline.lib.robot.tcp import at_tcp, in_flange
from pipeline.lib.robot.urdf import tcp_transforms
from pipeline.lib.runtime.compensation import reach_mm
from pipeline.lib.runtime.pathsolve import cycle_s, joint_speeds
from pipeline.lib.runtime.realtime import Realtime
from pipeline.lib.runtime.service import Malformed, RequestError, Service, describe

log = logger(__name__)
PATH = "/RPC2"
INVALID_PARAMS, NO_METHOD, INTERNAL = -32602, -32601, -32603       # the XML-RPC fault code convention
METHODS = ("compensate", "compensate_many", "compensate_list", "compensate_path", "compensate_pose")

PARAMS = ("robot", "compensate", "serve", "path")
REQUIRED = [MODEL_WEIGHTS, WORKSPACE_JSON]                # the trained artifacts it reads (the checkpoint
                                                          # carries its config and physics geometry)
SERVICE_KEYS = ("unreachable_mm", "max_iter", "budget_ms", "stall_iter", "stall_ratio", "max_batch",
                "batch_wait_ms", "max_items", "call_budget_ms", "lm_per_call", "compile",
                "max_path_samples")                                                        # lib/runtime/service.py's
LIMIT_KEYS = ("max_body_bytes", "timeout_s", "max_connections", "echo_chars", "refusal_delay_ms")          # the transport's


def check_artifacts(root: Path) -> None:
    try:
        require(root, REQUIRED)
    except ValueError as e:
        raise SystemExit(f"pipeline.commands.serve: {e}") from None


FAULT_LINES, FAULT_LINES_PER_S = 20, 1.0   # the faults' log lines: 20 at once, then one a second; the rest counted
MESSAGE_CHARS = 1000    # a RequestError's fault: the service's own words, every value of the request it echoes cut
                        # to 40 characters (service.describe); cut at serve.echo_chars, its advice was lost


def clip(text: str, n: int) -> str:
    """text cut to n characters (what a message or a log line may echo of a request)."""
    return text if len(text) <= n else text[:n - 3] + "..."


class Declared(ValueError):
    """A DOCTYPE or entity declaration in a request body."""


def refuse_declaration(*args):
    raise Declared("a DOCTYPE or entity declaration: refused (an XML-RPC call has none)")


class Unmarshaller(xmlrpc.client.Unmarshaller):
    """xmlrpc.client's, but an integer of more digits than any float holds is a signed inf, and a number or
    boolean its type does not read (`<double>abc</double>`) a service.Malformed: the field's check then
    names it, where int()'s ValueError past 4300 digits, or float()'s, was an HTTP 400 naming nothing."""
    dispatch = dict(xmlrpc.client.Unmarshaller.dispatch)

    def scalar(self, data, read, tag):
        try:
            read(self, data)
        except (ValueError, TypeError, ArithmeticError):   # int(), float(), Decimal, a boolean not 0/1
            self.append(Malformed(tag, clip(data.strip(), 40)))
            self._value = 0

    def end_int(self, data):
        text = data.strip()
        if len(text.lstrip("+-").lstrip("0")) > 309:
            self.append(-math.inf if text.startswith("-") else math.inf)
            self._value = 0
        else:
            self.scalar(data, xmlrpc.client.Unmarshaller.end_int, "int")
    for tag in ("i1", "i2", "i4", "i8", "int", "biginteger"):
        dispatch[tag] = end_int

    def end_double(self, data):
        self.scalar(data, xmlrpc.client.Unmarshaller.end_double, "double")
    dispatch["double"] = dispatch["float"] = end_double

    def end_bigdecimal(self, data):
        self.scalar(data, xmlrpc.client.Unmarshaller.end_bigdecimal, "bigdecimal")
    dispatch["bigdecimal"] = end_bigdecimal

    def end_boolean(self, data):
        self.scalar(data, xmlrpc.client.Unmarshaller.end_boolean, "boolean")
    dispatch["boolean"] = end_boolean


def parse_call(data: bytes, use_builtin_types: bool) -> tuple[tuple, str]:
    """(params, method name) of an XML-RPC call, as xmlrpc.client.loads reads it, but a Declared at the
    first DOCTYPE or entity declaration, before any entity is expanded (in any encoding expat reads)."""
    target = Unmarshaller(use_builtin_types=use_builtin_types)
    parser = expat.ParserCreate(None, None)
    parser.StartElementHandler, parser.EndElementHandler = target.start, target.end
    parser.CharacterDataHandler = target.data
    parser.StartDoctypeDeclHandler = parser.EntityDeclHandler = refuse_declaration
    parser.buffer_text = True
    target.xml(None, None)
    parser.Parse(data, True)
    params, method = target.close(), target.getmethodname()
    if method is None:
        raise ValueError("a methodResponse")
    return params, method


class Handler(SimpleXMLRPCRequestHandler):
    """POST /RPC2 only, within the server's limits; every refusal a 4xx, the connection then closed."""
    rpc_paths = (PATH,)                                   # any other path: 404
    default_request_version = "HTTP/1.0"                  # a garbled request line: a 400 with its status line
    protocol_version = "HTTP/1.1"                         # keep-alive: a client's calls share one connection
                                                          # and one server thread (HTTP/1.0 clients: closed)

    def setup(self):
        self.timeout = self.server.limits["timeout_s"]    # each read and write; the whole request: Server.watch
        super().setup()

    def handle_one_request(self):
        self.server.watch(self.connection)                # from here (or the answer before) to its body read
        super().handle_one_request()

    def parse_request(self):
        if not super().parse_request():                   # a malformed request line or headers: 400 sent
            return False
        if self.command != "POST":
            self.send_error(405, f"only POST to {PATH} (XML-RPC)")
            return False
        return True

    def do_POST(self):
        if not self.is_rpc_path_valid():
            return self.report_404()
        limit, length = self.server.limits["max_body_bytes"], self.headers.get("content-length")
        if length is None:
            return self.send_error(411, "Content-Length required")
        if not (length.strip().isascii() and length.strip().isdigit()):
            return self.send_error(400, f"bad Content-Length {clip(repr(length), 40)}")
        digits = length.strip().lstrip("0") or "0"           # not int() of 4300 digits and more: a ValueError
        if len(digits) > len(str(limit)) or int(digits) > limit:
            return self.refuse_unread(413, f"request body of {clip(digits, 40)} bytes, more than the limit of "
                                           f"{limit} (serve.max_body_bytes)")
        length = int(digits)
        data = self.rfile.read(length)                    # a TimeoutError: handle_one_request drops it
        if len(data) < length:
            self.close_connection = True                  # the client went away, or its deadline passed
            return
        self.server.watch(self.connection, None)          # read: the worker's time is not the client's
        data = self.decode_request_content(data)
        if data is None:
            return
        try:
            params, method = parse_call(data, self.server.use_builtin_types)
        except Declared as e:
            return self.send_error(400, str(e))
        except Exception as e:
            return self.send_error(400, f"not an XML-RPC call ({type(e).__name__})")
        body = self.server.respond(method, params)
        self.server.watch(self.connection)                # the answer taken within timeout_s
        self.send_response(200)
        self.send_header("Content-Type", "text/xml")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def decode_request_content(self, data: bytes) -> bytes | None:
        """The body, gzip-decoded when so sent, up to serve.max_body_bytes decoded (beyond: a 413, the rest
        never inflated); None when refused (the answer sent)."""
        encoding = self.headers.get("content-encoding", "identity").strip().lower()
        if encoding == "identity":
            return data
        if encoding != "gzip":
            return self.send_error(501, f"Content-Encoding {clip(repr(encoding), 40)} not supported (gzip, identity)")
        limit, inflate = self.server.limits["max_body_bytes"], zlib.decompressobj(16 + zlib.MAX_WBITS)
        try:
            out = inflate.decompress(data, limit + 1)
        except zlib.error:
            return self.send_error(400, "bad gzip content")
        if len(out) > limit:
            return self.send_error(413, f"request body inflating to more than the limit of {limit} bytes "
                                        f"(serve.max_body_bytes)")
        if not inflate.eof:
            return self.send_error(400, "bad gzip content (truncated)")
        return out

    def send_error(self, code, message=None, explain=None):
        """A refusal (4xx, 501), answered serve.refusal_delay_ms after it was decided: the thread sleeps (no
        CPU), so a client that sends bad requests back to back gets a few answers a second, not hundreds."""
        if code >= 400:
            time.sleep(self.server.limits["refusal_delay_ms"] / 1000.0)
        super().send_error(code, message, explain)

    def refuse_unread(self, code: int, message: str) -> None:
        """Answer code without reading the body; then discard what the client still sends (at most
        timeout_s), so that it reads the answer rather than a reset connection."""
        self.server.watch(self.connection, None)          # bounded here
        self.send_error(code, message)
        self.wfile.flush()
        try:
            self.connection.shutdown(socket.SHUT_WR)
            end = time.monotonic() + self.timeout
            while time.monotonic() < end and self.connection.recv(65536):
                pass
        except OSError:
            pass

    def log_message(self, format, *args):
        log.warning("%s", clip(f"{self.client_address[0]}: {format % args}", self.server.limits["echo_chars"]))


class Server(socketserver.ThreadingMixIn, SimpleXMLRPCServer):
    """SimpleXMLRPCServer, one thread per connection, at most max_connections; faults logged, never fatal.
    `limits`: the transport's (LIMIT_KEYS); `service`: lib/service.Service. A reaper thread shuts down each
    connection whose deadline (watch) has passed."""
    daemon_threads = True
    request_queue_size = 64                               # listen backlog: socketserver's 5 drops concurrent connects

    def __init__(self, address, limits: dict, service):
        self.limits, self.service = limits, service
        self.lock, self.open, self.closing = threading.Lock(), {}, threading.Event()   # open: socket -> deadline
        self.refused, self.refused_logged = 0, 0.0
        self.fault_lock, self.fault_lines, self.fault_t, self.faults_unlogged = threading.Lock(), FAULT_LINES, 0.0, 0
        super().__init__(address, requestHandler=Handler, allow_none=False, logRequests=False)
        tick = max(0.01, min(0.1, limits["timeout_s"] / 20))
        threading.Thread(target=self._reap, args=(tick,), name="connection reaper", daemon=True).start()

    def watch(self, conn, deadline: float | None = ...) -> None:
        """conn's deadline: timeout_s from now (the default), or None (none: the worker has the request)."""
        with self.lock:
            if conn in self.open:
                self.open[conn] = time.monotonic() + self.limits["timeout_s"] if deadline is ... else deadline

    def _reap(self, tick: float) -> None:
        while not self.closing.wait(tick):
            now = time.monotonic()
            with self.lock:
                for conn, deadline in self.open.items():
                    if deadline is not None and deadline <= now:
                        self.open[conn] = None
                        self._cut(conn)

    @staticmethod
    def _cut(conn) -> None:
        try:
            conn.shutdown(socket.SHUT_RDWR)               # its thread's read or write returns, the thread ends
        except OSError:
            pass

    def process_request(self, request, client_address):
        with self.lock:
            full = len(self.open) >= self.limits["max_connections"]
            if not full:
                self.open[request] = time.monotonic() + self.limits["timeout_s"]
        if not full:
            return super().process_request(request, client_address)
        n = self.limits["max_connections"]             # refused here, in the accepting thread: no thread
        body = f"{n} connections open, the limit (serve.max_connections): try again later\n".encode()
        try:
            request.settimeout(0.1)
            request.sendall(b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\nConnection: close\r\n"
                            b"Retry-After: 1\r\nContent-Length: %d\r\n\r\n%s" % (len(body), body))
        except OSError:
            pass
        self.shutdown_request(request)
        self.refused += 1
        if time.monotonic() - self.refused_logged > 10:
            self.refused_logged = time.monotonic()
            log.warning("%s: refused (503): %d connection(s) beyond serve.max_connections (%d) so far",
                        client_address[0], self.refused, n)

    def shutdown_request(self, request):
        with self.lock:
            self.open.pop(request, None)
        super().shutdown_request(request)

    def handle_error(self, request, client_address):
        """One line: the client and the exception (a reset connection is no bug of the server's)."""
        e = sys.exc_info()[1]
        log.warning("%s", clip(f"{client_address[0]}:{client_address[1]}: {type(e).__name__}: {e}",
                               self.limits["echo_chars"]))

    def respond(self, method: str, params: tuple) -> bytes:
        """The XML-RPC response (answer or Fault) to a parsed call."""
        try:
            answer = xmlrpc.client.dumps((self._dispatch(method, params),), methodresponse=True)
        except Fault as f:
            answer = xmlrpc.client.dumps(f)
        return answer.encode("utf-8", "xmlcharrefreplace")

    def log_fault(self, text: str, n: int) -> None:
        """A fault's log line, cut to n characters: FAULT_LINES at once, then FAULT_LINES_PER_S a second; those
        beyond are counted, and the next line logged says how many."""
        with self.fault_lock:
            now = time.monotonic()
            self.fault_lines = min(FAULT_LINES, self.fault_lines + (now - self.fault_t) * FAULT_LINES_PER_S)
            self.fault_t = now
            if self.fault_lines < 1:
                self.faults_unlogged += 1
                return
            self.fault_lines -= 1
            more, self.faults_unlogged = self.faults_unlogged, 0
        log.warning("%s", clip((f"({more} fault(s) not logged before this one) " if more else "") + text, n))

    def _dispatch(self, method, params):
        n = self.limits["echo_chars"]
        func = self.funcs.get(method)
        try:
            if func is None:                              # the name echoed last, so cutting spares the list
                raise Fault(NO_METHOD, clip(f"unknown method (methods: {', '.join(sorted(self.funcs))}): "
                                            f"{method!r}", n))
            try:
                inspect.signature(func).bind(*params)
            except TypeError:
                names = ", ".join(inspect.signature(func).parameters)
                raise Fault(INVALID_PARAMS, f"{method}: expected {len(inspect.signature(func).parameters)} "
                                            f"argument(s) ({names}), got {len(params)}") from None
            try:
                return func(*params)
            except RequestError as e:                     # the service's words, each value echoed cut (describe)
                n = MESSAGE_CHARS
                raise Fault(INVALID_PARAMS, clip(str(e), n)) from None
        except Fault as f:
            self.log_fault(f"fault: {f.faultString}" if func is None else f"{method}: fault: {f.faultString}", n)
            raise
        except Exception as e:                            # a bug, not a bad request: say so, keep serving
            log.exception("%s: internal error", method)
            raise Fault(INTERNAL, clip(f"{method}: internal error ({type(e).__name__}: {e})", n)) from None

    def server_close(self):
        self.closing.set()
        with self.lock:
            for conn in self.open:                        # their threads end, so closing waits for none
                self._cut(conn)
        super().server_close()
        self.service.close()


def fast_path(model, workspace: Workspace, limits_deg, tol_mm: float, graph: Path,
              tcp_mm=None) -> OnnxRealtime | None:
    """The controller path on onnxruntime from `graph` (the export stage's models/controller.onnx, or
    controller_physics.onnx for the physics alone; their _tcp graphs fed tcp_mm, flange frame), when it is
    there and answers as the PyTorch model does (on 8 training poses, 0.5 mm off: an export of another
    model would not); else None, with a warning saying why (the service then runs it in PyTorch)."""
    if not graph.exists():
        log.warning("no %s (run `dvc repro`): the controller path runs in PyTorch", graph)
        return None
    limits = np.radians(limits_deg)
    try:
        fast = OnnxRealtime(graph, limits, tol_mm, workspace, tcp_mm=tcp_mm)
    except ValueError as e:
        log.warning("%s; run `dvc repro`: the controller path runs in PyTorch", e)
        return None
    q0 = np.radians(workspace.train_q[:8])
    with torch.no_grad():
        target = model(torch.as_tensor(q0))[0].numpy() + [0.5, -0.3, 0.2]
    d = deviation(Realtime(model, limits, tol_mm, workspace=workspace), fast, q0, target)
    if d["max_q_rad"] > 1e-6 or d["max_residual_mm"] > 1e-4:
        log.warning("%s does not answer as %s (%.1e rad, %.1e mm apart: exported from another model?); run "
                    "`dvc repro`: the controller path runs in PyTorch", graph, MODEL_WEIGHTS,
                    d["max_q_rad"], d["max_residual_mm"])
        return None
    return fast


def by_name(introspect):
    """An introspection function that answers a method_name that is not a string with a RequestError."""
    def checked(method_name):
        if not isinstance(method_name, str):
            raise RequestError(f"method_name: expected a string, got {describe(method_name)}")
        return introspect(method_name)
    return checked


def make_server(params: dict, host: str | None = None, port: int | None = None,
                compile: bool | None = None, onnx: bool | None = None, tcp: str | None = None,
                root: Path = HERE) -> Server:
    """The service on host:port (None: the `serve:` section; port 0: a free port, in server.server_address),
    not yet serving: call serve_forever(). compile, onnx: override serve.compile, serve.onnx; tcp: answer
    for that `robot.tcp` point; root: the project whose trained artifacts it serves."""
    params = for_stage(params, PARAMS)
    cfg = params["serve"]
    cfg = {**cfg, **{k: v for k, v in (("compile", compile), ("onnx", onnx)) if v is not None}}
    host, port = cfg["host"] if host is None else host, cfg["port"] if port is None else port
    check_artifacts(root)
    torch.set_num_threads(cfg["torch_threads"])             # process-wide
    robot, workspace = load_robot(params["robot"]), Workspace.from_dict(read_json(root / WORKSPACE_JSON))
    limits_deg = robot.limits_deg
    try:
        speeds = joint_speeds(robot, params["path"]["joint_speed_deg_s"])
    except ValueError as e:                               # compensate_path says so; the rest serves
        speeds = str(e)
    model = served(load_model(root / MODEL_WEIGHTS), workspace.network)     # evaluate's verdict on the network
    graph = root / (CONTROLLER_ONNX if workspace.network else CONTROLLER_PHYSICS_ONNX)
    tcp_mm, g = None, model.physics.geometry()
    frame_rot = tool_rotation(g).numpy() if TOOL_ROT in g else None     # compensate_pose: the probe's frame
    if tcp is not None:                                   # every target a TCP's, on the graph fed its point
        model = at_tcp(model, params["robot"]["tcp"], tcp, theory_geometry(robot, robot.tool))[0]
        graph = root / (CONTROLLER_TCP_ONNX if workspace.network else CONTROLLER_PHYSICS_TCP_ONNX)
        flange_tcp = in_flange(params["robot"]["tcp"], g)                 # the TCP in the (calibrated) flange frame
        tcp_mm = flange_tcp[tcp]["xyz_mm"]
        frame_rot = tcp_transforms(flange_tcp)[tcp][:3, :3]                # or the TCP's
    tol = params["compensate"]["tol_mm"]
    controller = fast_path(model, workspace, limits_deg, tol, graph, tcp_mm) if cfg["onnx"] else None
    log.info("serving %s; the controller path on %s", "the whole model" if workspace.network else
             "the physics alone (the network did not lower the validation error)",
             f"onnxruntime ({graph})" if controller is not None else "PyTorch" + (", compiled" if cfg["compile"] else ""))
    service = Service(model, workspace, limits_deg, reach_mm(model.physics.geometry()), tol_mm=tol,
                      jacobian_of=params["compensate"]["jacobian_of"], controller=controller,
                      max_deviation_mm=params["path"]["max_deviation_mm"], joint_speed_deg_s=speeds,
                      frame_rot=frame_rot, tol_arcsec=params["compensate"]["tol_arcsec"],
                      path_timing=(params["path"]["accel_mm_s2"], params["path"]["corner_mm"], cycle_s(robot)),
                      **{k: cfg[k] for k in SERVICE_KEYS})
    try:
        server = Server((host, port), {k: cfg[k] for k in LIMIT_KEYS}, service)
    except OSError as e:
        service.close()
        raise SystemExit(f"pipeline.commands.serve: cannot listen on {host}:{port}: {e}") from None
    server.register_introspection_functions()
    for name in ("system.methodHelp", "system.methodSignature"):      # the standard library's take any value
        server.funcs[name] = by_name(server.funcs[name])
    for name in METHODS:
        server.register_function(getattr(service, name), name)
    return server


def url(server: Server) -> str:
    host, port = server.server_address[:2]
    return f"http://{host}:{port}{PATH}"


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m pipeline.commands.serve", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--port", type=int, default=None, help="TCP port (default: serve.port)")
    ap.add_argument("--host", default=None, help="address to listen on (default: serve.host; 0.0.0.0: every "
                                                 "interface, to serve a robot on the network)")
    ap.add_argument("--onnx", action=argparse.BooleanOptionalAction, default=None,
                    help="run the controller path on onnxruntime, models/controller.onnx (default: serve.onnx)")
    ap.add_argument("--compile", action=argparse.BooleanOptionalAction, default=None,
                    help="torch.compile the controller path when it runs in PyTorch (default: serve.compile)")
    ap.add_argument("--tcp", default=None, help="answer for this robot.tcp point (params.yaml), not the marker")
    add_project(ap)
    a = ap.parse_args(argv)
    if not (a.project / PARAMS_FILE).exists():
        missing = [str(p) for p in [PARAMS_FILE, *REQUIRED] if not (a.project / p).exists()]
        raise SystemExit(f"pipeline.commands.serve: missing {', '.join(missing)} in {a.project.resolve()}: run it in "
                         f"the project's root (where params.yaml is) or name it with --project, after `dvc repro`")
    try:
        server = make_server(load_params(a.project / PARAMS_FILE), a.host, a.port, a.compile, a.onnx, a.tcp, a.project)
    except (ParamsError, ValueError) as e:
        raise SystemExit(f"pipeline.commands.serve: {e}") from None
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

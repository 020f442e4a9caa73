"""`bench serve`: the compensation service (`python -m pipeline.commands.serve`, a subprocess on a free loopback
port) under load, its controller path on onnxruntime (models/controller.onnx, the default), in eager
PyTorch and compiled (`--paths`): startup time, then one client and `--clients` concurrent clients
calling `compensate` on the test points; latency percentiles, calls per second, failed calls, and the
concurrent clients' throughput over one client's. Writes reports/bench/serve.json (the paths run
replace theirs, the others kept). Needs a finished `dvc repro` in the project.

`bench serve --hostile`: 4 good clients beside one hostile client of each class (HOSTILE, a subprocess
of its own, stopped and let go on in turn) on the same server, and alone between: the share of their
calls/s they keep and their p99 latency over theirs alone. Writes reports/bench/serve_hostile.json."""
import gzip
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
import xmlrpc.client
from pathlib import Path

import numpy as np
import psutil

from pipeline.commands.bench.common import BENCH, ROOT, machine
from pipeline.lib.project.columns import JOINTS_DEG, THEORY
from pipeline.lib.project.config import load_params, logger, read_json, write_json
from pipeline.lib.reading.prepared import load_prepared

log = logger(__name__)


def test_targets() -> tuple[list, list]:
    """The project's test points: recorded angles (rad) and their theory positions (mm), as lists."""
    df = load_prepared(load_params()["robot"], parts=False).points
    test = df[df.split == "test"]
    return np.radians(test[JOINTS_DEG].to_numpy()).tolist(), test[THEORY].to_numpy().tolist()


def start_server(flags=(), stderr=None) -> tuple[subprocess.Popen, str, float]:
    """`python -m pipeline.commands.serve` (with `flags`) in a subprocess on a free loopback port, once it answers:
    (the process, its URL, the seconds it took to start); stop it with terminate()."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    url, t0 = f"http://127.0.0.1:{port}/RPC2", time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.commands.serve", "--port", str(port), *flags], stderr=stderr)
    while True:                                           # until it answers
        try:
            xmlrpc.client.ServerProxy(url).system.listMethods()
            return proc, url, time.perf_counter() - t0
        except OSError:
            if proc.poll() is not None or time.perf_counter() - t0 > 120:
                proc.kill()
                raise RuntimeError(f"python -m pipeline.commands.serve did not start (exit code {proc.wait()})") from None
            time.sleep(0.2)


def timed_call(proxy, q0: list, target: list) -> tuple[float, bool | None]:
    """One `compensate` call: its wall latency (ms), and whether it converged (None: it failed)."""
    t = time.perf_counter()
    try:
        converged = bool(proxy.compensate(q0, target)["converged"])
    except Exception:
        converged = None
    return 1000 * (time.perf_counter() - t), converged


def load_test(url: str, q0: list, tgt: list, clients: int, calls: int, server_pid: int | None = None) -> dict:
    """`clients` threads, each with its own ServerProxy, make calls/clients `compensate` calls on the
    (q0, target) pairs (cycled); each call's wall latency; with server_pid, the CPU time per call of the
    server's process and of this one (the clients'), and the cores each kept busy."""
    procs = {"server": psutil.Process(server_pid), "clients": psutil.Process()} if server_pid else {}
    cpu0 = {k: sum(p.cpu_times()[:2]) for k, p in procs.items()}
    ms, failed, unconverged = [[] for _ in range(clients)], [0] * clients, [0] * clients

    def client(k):
        proxy = xmlrpc.client.ServerProxy(url)
        for i in range(k, calls, clients):
            latency, converged = timed_call(proxy, q0[i % len(q0)], tgt[i % len(tgt)])
            failed[k] += converged is None
            unconverged[k] += converged is False
            ms[k].append(latency)
    threads = [threading.Thread(target=client, args=(k,)) for k in range(clients)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    seconds, lat = time.perf_counter() - t0, np.concatenate(ms)
    cpu = {k: sum(p.cpu_times()[:2]) - cpu0[k] for k, p in procs.items()}
    return {"clients": clients, "calls": len(lat), "failed": sum(failed), "not_converged": sum(unconverged),
            "ms_p50": float(np.percentile(lat, 50)), "ms_p90": float(np.percentile(lat, 90)),
            "ms_p99": float(np.percentile(lat, 99)), "ms_max": float(lat.max()), "calls_per_s": len(lat) / seconds,
            "seconds": seconds, **{f"{k}_cpu_ms_per_call": 1000 * c / len(lat) for k, c in cpu.items()},
            **{f"{k}_cores_busy": c / seconds for k, c in cpu.items()}}


FLAGS = {"onnx": ["--onnx"], "eager": ["--no-onnx", "--no-compile"], "compiled": ["--no-onnx", "--compile"]}


def bench_serve(clients: int = 8, calls: int = 10000, paths=("onnx", "eager", "compiled")) -> dict:
    """The compensation service under load: `python -m pipeline.commands.serve` in a subprocess on a free loopback
    port, for each controller path of `paths` (FLAGS); for each, one client (calls/10 calls: a call's own
    latency) then `clients` concurrent clients (calls in all), on the test points (recorded angles ->
    theory position, cycled). Needs a finished `dvc repro` in the project."""
    q0, tgt = test_targets()
    path = BENCH / "serve.json"
    old = read_json(path) if path.exists() else {}
    for v in old.values():                                # earlier runs' paths keep their machine
        if isinstance(v, dict) and "one_client" in v:
            v.setdefault("machine", old.get("machine"))
    out = {**old, "machine": machine(),
           "server": "python -m pipeline.commands.serve, a subprocess on 127.0.0.1 (the clients on the same machine)",
           "n_test_points": len(q0)}
    for name in paths:
        proc, url, startup = start_server(FLAGS[name])
        try:
            out[name] = {"startup_s": startup, "machine": machine(), "project": str(Path.cwd()),
                         "one_client": load_test(url, q0, tgt, 1, calls // 10, proc.pid),
                         "concurrent": load_test(url, q0, tgt, clients, calls, proc.pid)}
            out[name]["concurrent_over_one_client"] = (out[name]["concurrent"]["calls_per_s"]
                                                       / out[name]["one_client"]["calls_per_s"])
        finally:
            proc.terminate()
            proc.wait(timeout=30)
        for k in ("one_client", "concurrent"):
            r = out[name][k]
            log.info("serve %s, %d client(s): %d calls in %.1f s (%.0f calls/s), %d failed, %d not converged; "
                     "latency p50 %.1f ms, p90 %.1f ms, p99 %.1f ms, max %.1f ms; CPU a call: server %.2f ms, "
                     "clients %.2f ms", name, r["clients"], r["calls"], r["seconds"], r["calls_per_s"], r["failed"],
                     r["not_converged"], r["ms_p50"], r["ms_p90"], r["ms_p99"], r["ms_max"],
                     r["server_cpu_ms_per_call"], r["clients_cpu_ms_per_call"])
        log.info("serve %s: %d clients give %.2fx one client's calls/s", name, clients,
                 out[name]["concurrent_over_one_client"])
    write_json(path, out)
    return out


# hostile clients: each a loop, run by hostile_client in a process of its own until killed
ORIGIN = [[0.0] * 6, [0.0, 0.0, 0.0]]                      # within the joint limits and the reach, unreachable
HOSTILE = {
    "entity_expansion": "a billion laughs (0.5 KB: 10^9 characters once expanded), one after the other",
    "gzip_bomb": "87 KB of gzip inflating to 20 MB of XML-RPC (compensate_many), one after the other",
    "many_unreachable": "compensate_many of 1000 unreachable targets (the origin), one call after the other",
    "dribbling": "100 connections sending one byte a second each, reconnecting when closed",
    "unreachable": "compensate of one unreachable target (the origin), one call after the other",
}


def laughs() -> bytes:
    entities = "".join(f"<!ENTITY {c} \"{('&' + p + ';') * 10}\">" for p, c in zip("abcdefgh", "bcdefghi"))
    return (f"<?xml version='1.0'?><!DOCTYPE m [<!ENTITY a \"{'a' * 10}\">{entities}]><methodCall><methodName>"
            "compensate</methodName><params><param><value>&i;</value></param></params></methodCall>").encode()


def bomb(mb: float = 20.0) -> bytes:
    item = xmlrpc.client.dumps((ORIGIN,))[len("<params>\n<param>\n"):-len("</param>\n</params>\n")]
    n = int(mb * 1e6 / len(item))
    xml = xmlrpc.client.dumps((ORIGIN,) * 0, "compensate_many").replace(
        "<params>\n</params>", "<params><param><value><array><data>" + item * n + "</data></array></value></param></params>")
    return gzip.compress(xml.encode(), 9)


def post(host: str, port: int, body: bytes, headers: str = "") -> bytes:
    """body POSTed to /RPC2 on a fresh connection; what the server answers until it closes."""
    with socket.create_connection((host, port), timeout=30) as s:
        s.sendall(f"POST /RPC2 HTTP/1.0\r\nContent-Length: {len(body)}\r\n{headers}\r\n".encode() + body)
        out = b""
        while chunk := s.recv(65536):
            out += chunk
    return out


def dribble(host: str, port: int, n: int = 100, every: float = 1.0) -> None:
    """n connections, each sending one byte of a request every `every` s, a new one when the server closes it."""
    conns, due = {}, {}
    def fresh(k):
        try:
            s = socket.create_connection((host, port), timeout=5)
            s.setblocking(False)
            conns[k], due[k] = s, time.monotonic() + every
            s.send(b"P")
        except OSError:
            conns.pop(k, None)
            due[k] = time.monotonic() + every                # refused: retry later
    for k in range(n):
        fresh(k)
    print("ready", flush=True)
    while True:
        readable = select.select(list(conns.values()), [], [], 0.05)[0]
        for k, s in list(conns.items()):
            closed = False
            if s in readable:
                try:
                    s.recv(4096)                           # an answer (a refusal) or the close
                except OSError:
                    pass
                closed = True
            if not closed and time.monotonic() >= due[k]:
                try:
                    s.send(b"x")
                    due[k] = time.monotonic() + every
                except OSError:
                    closed = True
            if closed:
                s.close()
                del conns[k]
        for k in range(n):
            if k not in conns and time.monotonic() >= due.get(k, 0):
                fresh(k)


def hostile_client(kind: str, url: str) -> None:
    """One hostile client of HOSTILE's `kind` against the service at url, until killed."""
    host, port = url.split("//")[1].split("/")[0].rsplit(":", 1)
    port = int(port)
    if kind == "dribbling":
        return dribble(host, port)
    proxy = xmlrpc.client.ServerProxy(url)
    body = {"entity_expansion": laughs, "gzip_bomb": bomb}.get(kind, bytes)()
    print("ready", flush=True)
    while True:
        try:
            if kind == "entity_expansion":
                post(host, port, body)
            elif kind == "gzip_bomb":
                post(host, port, body, "Content-Encoding: gzip\r\n")
            elif kind == "many_unreachable":
                proxy.compensate_many([ORIGIN] * 1000)
            else:
                proxy.compensate(*ORIGIN)
        except (xmlrpc.client.Error, OSError):
            pass


def start_hostile(kind: str, url: str) -> subprocess.Popen:
    """hostile_client(kind, url) in a process of its own, once it is ready (its preparation done)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-c", "import sys; from pipeline.commands.bench.serve import hostile_client; "
                             "hostile_client(*sys.argv[1:])", kind, url], stdout=subprocess.PIPE, text=True, env=env)
    if proc.stdout.readline().strip() != "ready":
        proc.kill()
        raise RuntimeError(f"the hostile client {kind} did not start (exit code {proc.wait()})")
    return proc


def good_calls(url: str, q0: list, tgt: list, clients: int, seconds: float) -> tuple[list, int, float]:
    """`clients` threads calling compensate on the (q0, target) pairs for `seconds`: each call's latency
    (ms), the calls failed or not converged, the seconds taken."""
    stop, ms, bad = threading.Event(), [[] for _ in range(clients)], [0] * clients

    def client(k):
        proxy = xmlrpc.client.ServerProxy(url)
        for i in range(k, 10 ** 9, clients):
            if stop.is_set():
                return
            latency, converged = timed_call(proxy, q0[i % len(q0)], tgt[i % len(tgt)])
            bad[k] += not converged
            ms[k].append(latency)
    threads = [threading.Thread(target=client, args=(k,)) for k in range(clients)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    time.sleep(seconds)
    stop.set()
    for t in threads:
        t.join()
    return [v for m in ms for v in m], sum(bad), time.perf_counter() - t0


def summary(runs: list) -> dict:
    lat = np.array([v for r in runs for v in r[0]])
    return {"calls_per_s": len(lat) / sum(r[2] for r in runs), "ms_p50": float(np.percentile(lat, 50)),
            "ms_p99": float(np.percentile(lat, 99)), "calls": len(lat), "failed_or_not_converged": sum(r[1] for r in runs)}


def hostile_load(url: str, q0: list, tgt: list, seconds: float = 10.0, clients: int = 4, kinds=tuple(HOSTILE),
                 rounds: int = 3) -> dict:
    """`clients` good clients beside one hostile client of each kind in turn, `seconds` in all, in `rounds`
    rounds each, alternating with as long alone (the hostile process stopped, SIGSTOP, then let go on: a
    drift of the machine, busy with other work, falls on both alike): for each kind the good clients' calls/s
    beside it over theirs alone, and their p99 over theirs alone."""
    out, part = {"alone": {}, "beside": {}}, seconds / rounds
    for kind in kinds:
        proc, alone, beside = start_hostile(kind, url), [], []
        try:
            for _ in range(rounds):
                proc.send_signal(signal.SIGSTOP)
                time.sleep(0.2)
                alone.append(good_calls(url, q0, tgt, clients, part))
                proc.send_signal(signal.SIGCONT)
                time.sleep(0.2)                            # its loop going again
                beside.append(good_calls(url, q0, tgt, clients, part))
        finally:
            proc.kill()
            proc.wait()
        a, b = summary(alone), summary(beside)
        out["alone"][kind], out["beside"][kind] = a, {**b, "calls_per_s_share": b["calls_per_s"] / a["calls_per_s"],
                                                      "p99_ratio": b["ms_p99"] / a["ms_p99"]}
        time.sleep(0.5)
    return out


def bench_hostile(seconds: float = 10.0, clients: int = 4) -> dict:
    """The compensation service beside hostile clients: `python -m pipeline.commands.serve` in a subprocess on a free
    loopback port (the defaults of the serve: section), `clients` good clients on the test points alone and
    beside each class of HOSTILE (`seconds` each, and as long alone). Writes reports/bench/serve_hostile.json."""
    q0, tgt = test_targets()
    proc, url, _ = start_server(stderr=subprocess.DEVNULL)
    try:
        r = hostile_load(url, q0, tgt, seconds, clients)
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    out = {"machine": machine(), "project": str(Path.cwd()),
           "server": "python -m pipeline.commands.serve, a subprocess on 127.0.0.1 (the clients on the same machine)",
           "good_clients": clients, "seconds_beside_each": seconds, "rounds": 3, "n_test_points": len(q0), "hostile": HOSTILE, **r}
    write_json(BENCH / "serve_hostile.json", out)
    for k, v in r["beside"].items():
        a = r["alone"][k]
        log.info("serve, %d good clients alone: %.0f calls/s, p99 %.1f ms; beside %s: %.0f calls/s (%.0f%%), p99 "
                 "%.1f ms (%.1fx), %d failed or not converged", clients, a["calls_per_s"], a["ms_p99"], k,
                 v["calls_per_s"], 100 * v["calls_per_s_share"], v["ms_p99"], v["p99_ratio"],
                 v["failed_or_not_converged"])
    return out

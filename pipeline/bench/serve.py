"""`bench serve`: the compensation service (`python -m pipeline.serve`, a subprocess on a free loopback
port) under load, its controller path on onnxruntime (models/controller.onnx, the default), in eager
PyTorch and compiled (`--paths`): startup time, then one client and `--clients` concurrent clients
calling `compensate` on the test points; latency percentiles, calls per second, failed calls, and the
concurrent clients' throughput over one client's. Writes reports/bench/serve.json (the paths run
replace theirs, the others kept). Needs a finished `dvc repro` in the project."""
import socket
import subprocess
import sys
import threading
import time
import xmlrpc.client
from pathlib import Path

import numpy as np
import psutil

from ..lib.columns import JOINTS_DEG, THEORY
from ..lib.config import load_params, logger, read_json, write_json
from .common import BENCH, machine, prepared

log = logger(__name__)


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
            j = i % len(q0)
            t = time.perf_counter()
            try:
                unconverged[k] += not proxy.compensate(q0[j], tgt[j])["converged"]
            except Exception:
                failed[k] += 1
            ms[k].append(1000 * (time.perf_counter() - t))
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
    """The compensation service under load: `python -m pipeline.serve` in a subprocess on a free loopback
    port, for each controller path of `paths` (FLAGS); for each, one client (calls/10 calls: a call's own
    latency) then `clients` concurrent clients (calls in all), on the test points (recorded angles ->
    theory position, cycled). Needs a finished `dvc repro` in the project."""
    df = prepared(load_params())[0]
    test = df[df.split == "test"]
    q0, tgt = np.radians(test[JOINTS_DEG].to_numpy()).tolist(), test[THEORY].to_numpy().tolist()
    path = BENCH / "serve.json"
    old = read_json(path) if path.exists() else {}
    for v in old.values():                                # earlier runs' paths keep their machine
        if isinstance(v, dict) and "one_client" in v:
            v.setdefault("machine", old.get("machine"))
    out = {**old, "machine": machine(),
           "server": "python -m pipeline.serve, a subprocess on 127.0.0.1 (the clients on the same machine)",
           "n_test_points": len(q0)}
    for name in paths:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        url = f"http://127.0.0.1:{port}/RPC2"
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "pipeline.serve", "--port", str(port), *FLAGS[name]])
        try:
            while True:                                   # until it answers
                try:
                    xmlrpc.client.ServerProxy(url).system.listMethods()
                    break
                except OSError:
                    if proc.poll() is not None or time.perf_counter() - t0 > 120:
                        raise RuntimeError(f"python -m pipeline.serve did not start (exit code {proc.poll()})")
                    time.sleep(0.2)
            out[name] = {"startup_s": time.perf_counter() - t0, "machine": machine(), "project": str(Path.cwd()),
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

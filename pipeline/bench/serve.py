"""`bench serve`: the compensation service (`python -m pipeline.serve`, a subprocess on a free loopback
port) under load, eager and compiled: startup time, then one client and `--clients` concurrent clients
calling `compensate` on the test points; latency percentiles and calls per second. Writes
reports/bench/serve.json. Needs a finished `dvc repro` in the project."""
import socket
import subprocess
import sys
import threading
import time
import xmlrpc.client

import numpy as np

from ..lib.columns import JOINTS_DEG, THEORY
from ..lib.config import load_params, logger, write_json
from .common import BENCH, machine, prepared

log = logger(__name__)


def load_test(url: str, q0: list, tgt: list, clients: int, calls: int) -> dict:
    """`clients` threads, each with its own ServerProxy, make calls/clients `compensate` calls on the
    (q0, target) pairs (cycled); each call's wall latency."""
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
    return {"clients": clients, "calls": len(lat), "failed": sum(failed), "not_converged": sum(unconverged),
            "ms_p50": float(np.percentile(lat, 50)), "ms_p90": float(np.percentile(lat, 90)),
            "ms_p99": float(np.percentile(lat, 99)), "ms_max": float(lat.max()), "calls_per_s": len(lat) / seconds,
            "seconds": seconds}


def bench_serve(clients: int = 8, calls: int = 10000) -> dict:
    """The compensation service under load: `python -m pipeline.serve` in a subprocess on a free loopback
    port, eager and compiled (--compile); for each, one client (calls/10 calls: a call's own latency)
    then `clients` concurrent clients (calls in all), on the test points (recorded angles -> theory
    position, cycled). Needs a finished `dvc repro` in the project."""
    df = prepared(load_params())[0]
    test = df[df.split == "test"]
    q0, tgt = np.radians(test[JOINTS_DEG].to_numpy()).tolist(), test[THEORY].to_numpy().tolist()
    out = {"machine": machine(), "server": "python -m pipeline.serve, a subprocess on 127.0.0.1 (the clients "
                                           "on the same machine)", "n_test_points": len(q0)}
    for name, flag in (("eager", "--no-compile"), ("compiled", "--compile")):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        url = f"http://127.0.0.1:{port}/RPC2"
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "pipeline.serve", "--port", str(port), flag])
        try:
            while True:                                   # until it answers
                try:
                    xmlrpc.client.ServerProxy(url).system.listMethods()
                    break
                except OSError:
                    if proc.poll() is not None or time.perf_counter() - t0 > 120:
                        raise RuntimeError(f"python -m pipeline.serve did not start (exit code {proc.poll()})")
                    time.sleep(0.2)
            out[name] = {"startup_s": time.perf_counter() - t0,
                         "one_client": load_test(url, q0, tgt, 1, calls // 10),
                         "concurrent": load_test(url, q0, tgt, clients, calls)}
        finally:
            proc.terminate()
            proc.wait(timeout=30)
        for k in ("one_client", "concurrent"):
            r = out[name][k]
            log.info("serve %s, %d client(s): %d calls in %.1f s (%.0f calls/s), %d failed, %d not converged; "
                     "latency p50 %.1f ms, p90 %.1f ms, p99 %.1f ms, max %.1f ms", name, r["clients"], r["calls"],
                     r["seconds"], r["calls_per_s"], r["failed"], r["not_converged"], r["ms_p50"], r["ms_p90"],
                     r["ms_p99"], r["ms_max"])
    write_json(BENCH / "serve.json", out)
    return out

"""Run many independent jobs (training seeds, settings, robots) in order or on Ray.

    results = run(fn, jobs, engine="ray", address=None, cpus_per_job=1, desc="ablation")

`fn(job)` is a plain library call (no subprocess per job); results come back in the
order of `jobs`. engine "sequential": one after the other in this process;
"ray": one Ray task per job, on a local Ray instance started here (as many task slots
as cores) or, with `address` (or the RAY_ADDRESS environment variable), on that
cluster, whose every node needs this project installed (`pip install -e .`) and
reaches the data by the same paths. Each job runs with `cpus_per_job` torch threads
in either engine, so the two give the same numbers (a job's float reductions depend on
its thread count) and Ray's tasks do not oversubscribe the cores.
"""
import os
import time
from pathlib import Path

import torch
from tqdm import tqdm

ENGINES = ("sequential", "ray")
PROJECT = Path(__file__).resolve().parents[2]          # where a local Ray's workers import the package from


def threads_per_job(engine: str, threads: int | None = None) -> int:
    """torch threads per job: `threads` if given, else 1 on Ray (a task per core), every core in order."""
    return threads or (1 if engine == "ray" else torch.get_num_threads())


def _call(fn, job, threads: int):
    torch.set_num_threads(threads)
    t0 = time.perf_counter()
    return fn(job), time.perf_counter() - t0


def run(fn, jobs: list, engine: str = "sequential", address: str | None = None, cpus_per_job: int = 1,
        desc: str = "jobs", on_result=None) -> tuple[list, dict]:
    """Results of fn over jobs (in order) and timing: {"engine", "seconds", "job_seconds": [...]}.
    on_result(i, result), if given, is called as each job finishes (so a long sweep can save as it goes)."""
    if engine not in ENGINES:
        raise ValueError(f"unknown engine {engine!r}; use one of {ENGINES}")
    t0 = time.perf_counter()
    on_result = on_result or (lambda i, r: None)
    if engine == "sequential":
        threads = torch.get_num_threads()
        out = []
        try:
            for i, j in enumerate(tqdm(jobs, desc=desc)):
                out.append(_call(fn, j, cpus_per_job))
                on_result(i, out[-1][0])
        finally:
            torch.set_num_threads(threads)
    else:
        out = _ray(fn, jobs, address or os.environ.get("RAY_ADDRESS"), cpus_per_job, desc, on_result)
    return [r for r, _ in out], {"engine": engine, "seconds": time.perf_counter() - t0,
                                 "job_seconds": [s for _, s in out], "cpus_per_job": cpus_per_job}


def _ray(fn, jobs, address, cpus_per_job, desc, on_result):
    import ray
    started = not ray.is_initialized()
    if started:   # local: every core a task slot; the workers import the project from this tree
        ray.init(address=address, include_dashboard=False, log_to_driver=False, configure_logging=False,
                 runtime_env={"env_vars": {"PYTHONPATH": os.pathsep.join(
                     [str(PROJECT), os.environ.get("PYTHONPATH", "")])}} if address is None else None)
    try:
        task = ray.remote(num_cpus=cpus_per_job)(_call)
        fn_ref = ray.put(fn)
        refs = [task.remote(fn_ref, j, cpus_per_job) for j in jobs]
        index, pending = {r: i for i, r in enumerate(refs)}, list(refs)
        with tqdm(total=len(refs), desc=f"{desc} (ray)") as bar:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                on_result(index[done[0]], ray.get(done[0])[0])
                bar.update(len(done))
        return ray.get(refs)
    finally:
        if started:
            ray.shutdown()

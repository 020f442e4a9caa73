"""Run many independent jobs (training seeds, settings, robots) in order or on Ray.

    results, timing = run(fn, jobs, engine="ray", address=None, cpus_per_job=1, desc="ablation",
                          shared=data)

`fn(job)`, or `fn(job, shared)` when `shared` is given, is a plain library call (no subprocess
per job); results come back in the order of `jobs`. engine "sequential": one after the other in
this process; "ray": one Ray task per job, spread over the nodes, on a local Ray instance started
here (as many task slots as cores) or, with `address` (or the RAY_ADDRESS environment variable),
on that cluster.

Nothing of the project has to be on a Ray node, and no filesystem is shared:
- the code travels with the tasks: Ray's runtime environment (`py_modules`) ships the `pipeline`
  package folder (no caches, no data, no reports), and a worker imports it from there;
- the data travel as values: `shared` (what every job reads, e.g. the aligned points and the
  geometries) is put once into Ray's object store and fetched once per node; each job carries its
  own values; results come back as values. A folder travels as {relative path: bytes} (`pack`,
  `unpack`): a robot's campaign to its task and its outputs back, a prepared scratch directory to
  every seed.
A node needs Python and the packages (constraints.txt), nothing else.

Each job runs with `cpus_per_job` torch threads in either engine, so the two give the same numbers
(a job's float reductions depend on its thread count) and Ray's tasks do not oversubscribe the cores.
timing["job_nodes"] (Ray: the node id each job ran on) and timing["job_code"] (the folder each job
imported `pipeline` from) say where the work ran and which code it ran.

A job that raises does not stop the others (in either engine): every job runs, each result is handed
to on_result as it comes, and then `run` raises SweepFailed, which names each failed job (its index,
the job and the error in one line) and carries the results of the others (None where a job failed)
and the timing, so a caller can write what finished and say what did not.
"""
import os
import time
from pathlib import Path

import torch
from tqdm import tqdm

ENGINES = ("sequential", "ray")
CODE_ROOT = Path(__file__).resolve().parents[3]   # holds the `pipeline` package this process runs: the
PACKAGE = CODE_ROOT / "pipeline"                  # project, or on a Ray worker the copy shipped with the job
_NO_SHARED = object()


class SweepFailed(RuntimeError):
    """Some jobs of a sweep raised; every other job ran. failures: [(index, job, "Type: message")];
    results: one per job (None where it failed); timing: as `run` returns it."""

    def __init__(self, desc: str, failures: list, results: list, timing: dict):
        self.failures, self.results, self.timing = failures, results, timing
        said = "; ".join(f"job {i} ({job!r:.80}): {err}" for i, job, err in failures)
        super().__init__(f"{desc}: {len(failures)} of {len(results)} job(s) failed, the others finished: {said}")


def _said(e: BaseException) -> str:
    """An error in one line: its type and message (a Ray task's error: the error it wraps)."""
    e = getattr(e, "cause", None) or e
    text = " ".join(str(e).split()) or "(no message)"
    return f"{type(e).__name__}: {text}"


def runtime_env() -> dict:
    """What travels with a Ray job, so with each of its tasks: the `pipeline` package's code
    (py_modules), without caches. `run` starts Ray with it; a caller that starts Ray itself (ray.init)
    passes runtime_env=runtime_env() (Ray uploads a local folder only for a whole job)."""
    return {"py_modules": [str(PACKAGE)], "excludes": ["__pycache__/", "*.pyc"]}


def pack(folder, skip=()) -> dict[str, bytes]:
    """Every file under `folder` (not under a top-level name in `skip`) as {relative posix path: bytes}:
    a folder as a value, to travel in a job or come back in a result."""
    folder = Path(folder)
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.relative_to(folder).parts[0] not in skip}


def unpack(files: dict[str, bytes], folder) -> Path:
    """Write `pack`'s {relative path: bytes} under `folder` (made if absent; files there are replaced)."""
    folder = Path(folder)
    for name, data in files.items():
        path = folder / name
        if Path(name).is_absolute() or ".." in Path(name).parts:
            raise ValueError(f"unpack: {name!r} is not a path inside the folder")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    return folder


def threads_per_job(engine: str, threads: int | None = None) -> int:
    """torch threads per job: `threads` if given, else 1 on Ray (a task per core), every core in order."""
    return threads or (1 if engine == "ray" else torch.get_num_threads())


def _call(fn, job, threads: int, *shared):
    torch.set_num_threads(threads)
    t0 = time.perf_counter()
    return fn(job, *shared), time.perf_counter() - t0


def _task(fn, job, threads: int, *shared):
    """_call on a Ray worker, with the node it ran on and where it imported the code from."""
    import ray
    result, seconds = _call(fn, job, threads, *shared)
    return result, seconds, ray.get_runtime_context().get_node_id(), str(CODE_ROOT)


def run(fn, jobs: list, engine: str = "sequential", address: str | None = None, cpus_per_job: int = 1,
        desc: str = "jobs", on_result=None, shared=_NO_SHARED) -> tuple[list, dict]:
    """Results of fn over jobs (in order) and timing: {"engine", "seconds", "job_seconds": [...],
    "job_nodes": [...], "job_code": [...]}. shared, if given, is passed to every call as fn(job, shared)
    (on Ray: put once into the object store). on_result(i, result), if given, is called as each job
    finishes (so a long sweep can save as it goes, or write and drop what a result carries)."""
    if engine not in ENGINES:
        raise ValueError(f"unknown engine {engine!r}; use one of {ENGINES}")
    t0 = time.perf_counter()
    on_result = on_result or (lambda i, r: None)
    extra = () if shared is _NO_SHARED else (shared,)
    failures = []
    if engine == "sequential":
        threads = torch.get_num_threads()
        out = []
        try:
            for i, j in enumerate(tqdm(jobs, desc=desc)):
                t1 = time.perf_counter()
                try:
                    out.append((*_call(fn, j, cpus_per_job, *extra), None, str(CODE_ROOT)))
                except Exception as e:                # the others still run; said at the end
                    failures.append((i, j, _said(e)))
                    out.append((None, time.perf_counter() - t1, None, str(CODE_ROOT)))
                    continue
                on_result(i, out[-1][0])
        finally:
            torch.set_num_threads(threads)
    else:
        out = _ray(fn, jobs, address or os.environ.get("RAY_ADDRESS"), cpus_per_job, desc, on_result, extra,
                   failures)
    results = [r[0] for r in out]
    timing = {"engine": engine, "seconds": time.perf_counter() - t0,
              "job_seconds": [r[1] for r in out], "cpus_per_job": cpus_per_job,
              "job_nodes": [r[2] for r in out], "job_code": [r[3] for r in out]}
    if failures:
        raise SweepFailed(desc, sorted(failures, key=lambda f: f[0]), results, timing)
    return results, timing


def _ray(fn, jobs, address, cpus_per_job, desc, on_result, extra, failures):
    import ray
    started = not ray.is_initialized()
    if started:   # local (every core a task slot) or the cluster at `address`; the code goes with the job
        ray.init(address=address, include_dashboard=False, log_to_driver=False, configure_logging=False,
                 runtime_env=runtime_env())
    try:
        task = ray.remote(_task).options(num_cpus=cpus_per_job, scheduling_strategy="SPREAD")
        fn_ref, shared_refs = ray.put(fn), [ray.put(s) for s in extra]      # once, however many jobs
        index = {task.remote(fn_ref, j, cpus_per_job, *shared_refs): i for i, j in enumerate(jobs)}
        out, pending = [None] * len(jobs), list(index)
        with tqdm(total=len(jobs), desc=f"{desc} (ray)") as bar:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                i = index.pop(done[0])
                bar.update(len(done))
                try:
                    out[i] = ray.get(done[0])
                except Exception as e:                # the others still run; said at the end
                    failures.append((i, jobs[i], _said(e)))
                    out[i] = (None, None, None, None)
                    continue
                on_result(i, out[i][0])
        return out
    finally:
        if started:
            ray.shutdown()

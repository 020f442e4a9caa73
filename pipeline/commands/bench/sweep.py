"""`bench sweep`: a reduced ablation (groups x seeds, a few epochs each) run in order and as Ray tasks on a
local Ray instance, their wall times and speed-up, and the per-task overhead Ray adds (trivial tasks, with
and without its startup). Writes reports/bench/sweep.json. Needs a finished `dvc repro` in the project."""
import os
import time

from pipeline.commands.bench.common import BENCH, machine
from pipeline.lib.learning import sweep                                   # lib/learning/sweep.py: jobs in order or as Ray tasks
from pipeline.lib.learning.ablations import Data, Job, train_one
from pipeline.lib.project.config import load_params, logger, write_json
from pipeline.lib.reading.prepared import load_prepared

log = logger(__name__)


def noop(x):
    return x


def bench_sweep(groups=("baseline", "no_resnet"), seeds=(139, 140), epochs: int = 40) -> dict:
    """A reduced ablation (groups x seeds, `epochs` each) run sequentially (torch on every core) and as
    Ray tasks on a local Ray instance (one thread each, a task per core), on the project's prepared inputs
    (a value each job shares; nothing is written); and the per-task overhead Ray adds (trivial tasks).
    Needs a finished `dvc repro` in the project."""
    params = load_params()
    params["ablation"].update(seeds=list(seeds), max_epochs=epochs)
    cores = os.cpu_count() or 1
    prep = load_prepared(params["robot"])
    df, geometries = prep.points, prep.geometries()
    p = {k: params[k] for k in ("model", "loss", "train", "workspace", "ablation")}
    jobs, data = [Job(p, g, s) for g in groups for s in seeds], Data(df, geometries)
    out = {"machine": machine(), "what": f"ablation groups {list(groups)} x seeds {list(seeds)}, {epochs} epochs "
                                         "each (the full ablation: 8 groups x 5 seeds, up to 400 epochs)"}
    for engine, threads in (("sequential", cores), ("ray", 1)):
        runs, timing = sweep.run(train_one, jobs, engine, None, threads, desc=f"sweep {engine}", shared=data)
        out[engine] = {**timing, "test_3d_mae": [r["test"]["3d"]["mae"] for r in runs]}
    out["speedup_ray_over_sequential"] = out["sequential"]["seconds"] / out["ray"]["seconds"]
    n = 64
    _, seq = sweep.run(noop, list(range(n)), "sequential", desc="noop")
    t0 = time.perf_counter()
    sweep.run(noop, list(range(n)), "ray", desc="noop")
    with_startup = time.perf_counter() - t0
    import ray                                            # the same, Ray already up: the per-task cost alone
    ray.init(include_dashboard=False, log_to_driver=False, configure_logging=False,
             runtime_env=sweep.runtime_env())              # the package's code goes with the job
    try:
        sweep.run(noop, list(range(n)), "ray", desc="noop warm-up")
        _, warm = sweep.run(noop, list(range(n)), "ray", desc="noop")
    finally:
        ray.shutdown()
    out["overhead"] = {"tasks": n, "ray_seconds_with_startup": with_startup, "sequential_seconds": seq["seconds"],
                       "ms_per_task_after_startup": 1000 * warm["seconds"] / n,
                       "startup_s": with_startup - warm["seconds"]}
    write_json(BENCH / "sweep.json", out)
    log.info("sweep: sequential %.0f s, ray %.0f s (%.2fx); ray per task %.1f ms, startup %.1f s",
             out["sequential"]["seconds"], out["ray"]["seconds"], out["speedup_ray_over_sequential"],
             out["overhead"]["ms_per_task_after_startup"], out["overhead"]["startup_s"])
    return out

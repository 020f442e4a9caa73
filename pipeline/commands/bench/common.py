"""What the benchmarks share: where they write (BENCH) and find the public datasets (DATASETS),
the machine they ran on and a median timer. Writes nothing."""
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch


ROOT = Path(__file__).resolve().parents[3]              # the project: pipeline/commands/bench/common.py -> ./
DATASETS = ROOT.parent / "shared" / "datasets"
BENCH = ROOT / "reports" / "bench"


def machine() -> dict:
    cpu = next((l.split(":", 1)[1].strip() for l in Path("/proc/cpuinfo").read_text().splitlines()
                if l.startswith("model name")), platform.processor()) if Path("/proc/cpuinfo").exists() else ""
    return {"cpu": cpu, "cores": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__, "python": platform.python_version(), "platform": platform.platform()}


def timed(fn, repeats: int) -> float:
    """Median wall time (s) of fn() over repeats, after one warm-up call."""
    fn()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))

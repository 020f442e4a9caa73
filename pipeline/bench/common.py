"""What the benchmarks share: where they write (BENCH) and find the public datasets (DATASETS),
the machine they ran on, a median timer, and the pipeline's prepared points. Writes nothing."""
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

from ..lib.artifacts import CALIBRATED_GEOMETRY, FRAME_JSON, PARTS_JSON, load_points
from ..lib.config import read_json
from ..lib.geometry import Calibration, aligned, theory_geometry, with_parts
from ..lib.robots import load_robot

ROOT = Path(__file__).resolve().parents[2]              # the project: pipeline/bench/common.py -> ./
DATASETS = ROOT.parent / "shared" / "datasets"
BENCH = ROOT / "reports" / "bench"


def prepared(params: dict) -> tuple:
    """The pipeline's aligned points and the physics geometries {"calibrated" (with the error maps),
    "nominal"}, from the stage outputs here."""
    calibration = Calibration.from_dict(read_json(CALIBRATED_GEOMETRY))
    nominal = theory_geometry(load_robot(params["robot"]), read_json(FRAME_JSON)["tool_mm"])
    geometries = {"calibrated": with_parts(calibration.geometry, read_json(PARTS_JSON)), "nominal": nominal}
    return aligned(load_points(), calibration, nominal), geometries


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

"""`bench export`: the export stage's ONNX graphs, exported `rounds` times on the project's trained model
(models/boter.pt) in the order the stage writes them, into a scratch folder (nothing of the project is
overwritten): the seconds of each export and each file's nodes. Writes reports/bench/export.json. Needs a
finished `dvc repro` in the project (run it in the project's folder)."""
import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline.commands.bench.common import BENCH, machine
from pipeline.lib.learning.checkpoint import load_model
from pipeline.lib.learning.model import PhysicsOnly
from pipeline.lib.learning.onnx_model import export_controller, export_onnx
from pipeline.lib.project.artifacts import HERE, MODEL_WEIGHTS, require
from pipeline.lib.project.config import logger, write_json

log = logger(__name__)


def exports(model) -> dict:
    """{what: (export(folder), the files it writes)}: the export stage's ONNX exports, in its order."""
    physics = PhysicsOnly(model)
    return {
        "model": (lambda d: export_onnx(model, d / "model.onnx"), ["model.onnx"]),
        "controller_tcp and controller (one trace)":
            (lambda d: export_controller(model, d / "controller_tcp.onnx", at_tcp=True, probe_path=d / "controller.onnx"),
             ["controller_tcp.onnx", "controller.onnx"]),
        "controller_physics_tcp and controller_physics (one trace)":
            (lambda d: export_controller(physics, d / "controller_physics_tcp.onnx", at_tcp=True,
                                         probe_path=d / "controller_physics.onnx"),
             ["controller_physics_tcp.onnx", "controller_physics.onnx"]),
        "controller_pose": (lambda d: export_controller(model, d / "controller_pose.onnx", pose=True),
                            ["controller_pose.onnx"]),
    }


def bench_export(rounds: int = 2) -> dict:
    import onnx
    require(HERE, [MODEL_WEIGHTS])
    model = load_model(MODEL_WEIGHTS)
    steps = exports(model)
    seconds = {what: [] for what in steps}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for r in range(rounds):
            for what, (export, _) in steps.items():
                t = time.perf_counter()
                export(folder)
                seconds[what].append(time.perf_counter() - t)
                log.info("export, round %d of %d: %s in %.1f s", r + 1, rounds, what, seconds[what][-1])
        nodes = {f: len(onnx.load(str(folder / f)).graph.node) for _, files in steps.values() for f in files}
    total = [sum(s[r] for s in seconds.values()) for r in range(rounds)]
    out = {"machine": machine(), "model": model.config, "rounds": rounds,
           "what": "each ONNX export of the export stage on the project's trained model, in the stage's order "
                   "(the stage also reads each file back: onnxruntime against PyTorch)",
           "seconds": seconds, "seconds_median": {k: float(np.median(v)) for k, v in seconds.items()},
           "seconds_all_rounds": total, "nodes": nodes}
    write_json(BENCH / "export.json", out)
    log.info("export: the six graphs in %s s (rounds)", " / ".join(f"{t:.0f}" for t in total))
    return out

"""`bench export`: the export stage's ONNX graphs (onnx_model.export_all), exported `rounds` times on the
project's trained model (models/boter.pt) into a scratch folder (nothing of the project is overwritten):
the seconds of each trace and each file's nodes. Writes reports/bench/export.json. Needs a finished
`dvc repro` in the project (run it in the project's folder)."""
import tempfile
from pathlib import Path

import numpy as np

from pipeline.commands.bench.common import BENCH, machine
from pipeline.lib.learning.checkpoint import load_model
from pipeline.lib.learning.onnx_model import export_all
from pipeline.lib.project.artifacts import HERE, MODEL_WEIGHTS, ONNX_FILES, require
from pipeline.lib.project.config import logger, write_json

log = logger(__name__)


def bench_export(rounds: int = 2) -> dict:
    import onnx
    require(HERE, [MODEL_WEIGHTS])
    model = load_model(MODEL_WEIGHTS)
    seconds = {}
    with tempfile.TemporaryDirectory() as tmp:
        paths = {f.stem: Path(tmp) / f.name for f in ONNX_FILES}
        for r in range(rounds):
            log.info("export, round %d of %d", r + 1, rounds)
            for what, s in export_all(model, paths).items():
                seconds.setdefault(what, []).append(s)
        nodes = {p.name: len(onnx.load(str(p)).graph.node) for p in paths.values()}
    total = [sum(s[r] for s in seconds.values()) for r in range(rounds)]
    out = {"machine": machine(), "model": model.config, "rounds": rounds,
           "what": "each ONNX export of the export stage on the project's trained model, in the stage's order "
                   "(the stage also reads each file back: onnxruntime against PyTorch)",
           "seconds": seconds, "seconds_median": {k: float(np.median(v)) for k, v in seconds.items()},
           "seconds_all_rounds": total, "nodes": nodes}
    write_json(BENCH / "export.json", out)
    log.info("export: the six graphs in %s s (rounds)", " / ".join(f"{t:.0f}" for t in total))
    return out

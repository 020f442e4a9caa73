"""The DVC stages of ./dvc.yaml, one module each: each reads its params and files, calls the library and
writes its outputs. No stage imports another, nor a command. And the one way to run a stage:

    run(name, argv=(), root=HERE)   stage `name` in this process on the project at `root` (its
                                    params.yaml, its artifacts); the stage's main(argv, root)

dvc.yaml runs `python -m pipeline.stages.<name>`, which is main on the working directory; the
benchmarks, ablations, fleets and tests call run() (docs/decisions.md)."""
import importlib
from pathlib import Path

from pipeline.lib.project.artifacts import HERE

NAMES = ("ingest", "frame", "theory", "split", "calibrate", "parts", "train", "baselines", "evaluate",
         "compensate", "validate", "export", "report")          # in dvc.yaml's order


def run(name: str, argv=(), root: Path | str = HERE):
    """Stage `name` with arguments `argv` on the project at `root`; returns what its main returns."""
    if name not in NAMES:
        raise ValueError(f"no stage {name!r}; the stages: {', '.join(NAMES)}")
    return importlib.import_module(f"{__name__}.{name}").main(list(argv), Path(root))

"""Benchmarks, written as JSON under reports/bench/ (one module each: pipeline/bench/<name>.py).

    python -m pipeline.bench real  [--seeds 139 140 ...] [--engine ray]   the real sets in ../shared/datasets
    python -m pipeline.bench real --sets twin twin-2stations   the twin, from one and two stations
    python -m pipeline.bench speed [--soak 600] [--rounds 20]   training, prediction, compensation timings, the
                                                            controller path (PyTorch vs onnxruntime, alternating) and a soak
    python -m pipeline.bench speed --only controller        the controller path's part alone
    python -m pipeline.bench serve [--clients 8 --calls 10000]   the compensation service under load
    python -m pipeline.bench sweep                          a reduced ablation, in order vs on a local Ray
"""
import argparse

from ..lib.sweep import ENGINES
from .real import REAL_SETS, bench_real
from .serve import bench_serve
from .speed import bench_speed
from .sweep import bench_sweep


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m pipeline.bench", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["real", "speed", "serve", "sweep"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[139], help="training seeds (real)")
    ap.add_argument("--epochs", type=int, default=None, help="override train.max_epochs (real)")
    ap.add_argument("--sets", nargs="+", choices=list(REAL_SETS), default=None,
                    help="sets to run (default: the real ones; twin and twin-2stations on request)")
    ap.add_argument("--dnn", action=argparse.BooleanOptionalAction, default=True,
                    help="also train the paper's DNN baseline (every seed)")
    ap.add_argument("--other-physics", action=argparse.BooleanOptionalAction, default=True,
                    help="also train SPI-BoTER on the other physics branch (first seed)")
    ap.add_argument("-S", "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override a params.yaml value for the run (real), as dvc exp run -S: "
                         "train.ema=0.999; recorded in the output under the set's name + '@' + overrides")
    ap.add_argument("--engine", choices=ENGINES, default="sequential",
                    help="real: the seeds in order, or as Ray tasks (lib/sweep.py)")
    ap.add_argument("--address", default=None, help="real: a Ray cluster (default: RAY_ADDRESS, else local)")
    ap.add_argument("--threads", type=int, default=None, help="real: torch threads per seed (default: every "
                                                              "core in order, 1 on Ray)")
    ap.add_argument("--clients", type=int, default=8, help="concurrent clients (serve)")
    ap.add_argument("--calls", type=int, default=10000, help="compensate calls in all (serve)")
    ap.add_argument("--paths", nargs="+", choices=["onnx", "eager", "compiled"], default=["onnx", "eager", "compiled"],
                    help="serve: the controller paths to start the service with, one after the other")
    ap.add_argument("--soak", type=float, default=600.0, help="speed: seconds of the onnxruntime controller path alone")
    ap.add_argument("--rounds", type=int, default=20,
                    help="speed: rounds over the test targets, the controller paths interleaved call by call")
    ap.add_argument("--torch-threads", type=int, default=1,
                    help="speed: torch threads of the PyTorch controller path in the comparison (onnxruntime: 1)")
    ap.add_argument("--only", choices=["controller"], default=None,
                    help="speed: only the controller path's part (replaces that part of speed.json)")
    a = ap.parse_args(argv)
    if a.what == "real":
        bench_real(a.seeds, a.epochs, a.sets, a.other_physics, a.overrides, a.engine, a.address, a.threads, a.dnn)
    elif a.what == "serve":
        bench_serve(a.clients, a.calls, a.paths)
    elif a.what == "sweep":
        bench_sweep()
    else:
        bench_speed(a.soak, a.rounds, a.only, a.torch_threads)


if __name__ == "__main__":
    main()

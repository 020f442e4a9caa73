"""Benchmarks, written as JSON under reports/bench/ (one module each: pipeline/commands/bench/<name>.py).

    python -m pipeline.commands.bench real  [--seeds 139 140 ...] [--engine ray]   the real sets in ../shared/datasets
    python -m pipeline.commands.bench real --sets twin twin-2stations   the twin, from one and two stations
    python -m pipeline.commands.bench speed [--soak 600] [--rounds 20]   training, prediction, compensation timings, the
                                                            controller path (PyTorch vs onnxruntime, alternating) and a soak
    python -m pipeline.commands.bench speed --only controller        the controller path's part alone
    python -m pipeline.commands.bench serve [--clients 8 --calls 10000]   the compensation service under load
    python -m pipeline.commands.bench serve --hostile [--seconds 10]   4 good clients beside each class of hostile client
    python -m pipeline.commands.bench sweep                          a reduced ablation, in order vs on a local Ray
    python -m pipeline.commands.bench plan [--n 60 --seeds 139 140 141]   the measurement planner's loop closed on the twin
    python -m pipeline.commands.bench plan --curve [--sizes 25 50 100 200 400 700]   error against the poses measured
    python -m pipeline.commands.bench path [--spacings 0.5 1 2 5 10 20 50]   a path compensated sample by sample against
                                                            its waypoints alone, judged on the twin
    python -m pipeline.commands.bench export [--rounds 2]        the export stage's ONNX exports, each timed, and
                                                            their graphs' nodes
    python -m pipeline.commands.bench scale [--rows 10000 30000 300000 --programs 200000]   ingest and the program
                                                            compensator at scale: time and peak memory
"""
import argparse
import sys

from pipeline.commands.bench.export import bench_export
from pipeline.commands.bench.path import PATHS, SPACINGS, bench_path
from pipeline.commands.bench.plan import VARIANTS, bench_plan
from pipeline.commands.bench.real import REAL_SETS, bench_real
from pipeline.commands.bench.scale import bench_scale
from pipeline.commands.bench.serve import bench_hostile, bench_serve
from pipeline.commands.bench.speed import bench_speed
from pipeline.commands.bench.sweep import bench_sweep
from pipeline.lib.learning.sweep import ENGINES


def at_least(lo: int):
    """argparse type: an integer >= lo (a bad count is a one-line usage error, not a traceback or a
    silent default)."""
    def check(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"an integer >= {lo}, got {v}")
        return v
    return check


def positive(text: str) -> float:
    """argparse type: a finite number > 0."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (0 < v < float("inf")):
        raise argparse.ArgumentTypeError(f"a finite number > 0, got {text}")
    return v


def run(argv=None):
    ap = argparse.ArgumentParser(prog="python -m pipeline.commands.bench", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["real", "speed", "serve", "sweep", "plan", "scale", "path", "export"])
    ap.add_argument("--seeds", type=at_least(0), nargs="+", default=None,
                    help="training seeds (real: 139; plan: 139 140 141, each also the seed of its measurements)")
    ap.add_argument("--epochs", type=at_least(1), default=None, help="override train.max_epochs (real, plan)")
    ap.add_argument("--sets", nargs="+", choices=list(REAL_SETS), default=None,
                    help="sets to run (default: the real ones; twin and twin-2stations on request)")
    ap.add_argument("--dnn", action=argparse.BooleanOptionalAction, default=True,
                    help="also train the paper's DNN baseline (every seed)")
    ap.add_argument("--other-physics", action=argparse.BooleanOptionalAction, default=True,
                    help="also train SPI-BoTER on the other physics branch (first seed)")
    ap.add_argument("-S", "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override a params.yaml value for the run (real, plan), as dvc exp run -S: "
                         "train.ema=0.999; recorded in the output under the set's name + '@' + overrides")
    ap.add_argument("--engine", choices=ENGINES, default="sequential",
                    help="real: the seeds in order, or as Ray tasks (lib/learning/sweep.py)")
    ap.add_argument("--address", default=None, help="real: a Ray cluster (default: RAY_ADDRESS, else local)")
    ap.add_argument("--threads", type=at_least(1), default=None, help="real: torch threads per seed (default: every "
                                                              "core in order, 1 on Ray); plan: torch threads")
    ap.add_argument("--clients", type=at_least(1), default=8, help="concurrent clients (serve)")
    ap.add_argument("--calls", type=at_least(10), default=10000, help="compensate calls in all (serve)")
    ap.add_argument("--paths", nargs="+", choices=["onnx", "eager", "compiled"], default=["onnx", "eager", "compiled"],
                    help="serve: the controller paths to start the service with, one after the other")
    ap.add_argument("--hostile", action="store_true",
                    help="serve: 4 good clients alone, then beside each class of hostile client (serve_hostile.json)")
    ap.add_argument("--seconds", type=positive, default=10.0, help="serve --hostile: seconds of each phase")
    ap.add_argument("--soak", type=positive, default=600.0, help="speed: seconds of the onnxruntime controller path alone")
    ap.add_argument("--rounds", type=at_least(1), default=None,
                    help="speed: rounds over the test targets, the controller paths interleaved call by call "
                         "(default 20); export: rounds of the six exports (default 2)")
    ap.add_argument("--torch-threads", type=at_least(1), default=1,
                    help="speed: torch threads of the PyTorch controller path in the comparison (onnxruntime: 1)")
    ap.add_argument("--only", choices=["controller"], default=None,
                    help="speed: only the controller path's part (replaces that part of speed.json)")
    ap.add_argument("--n", type=at_least(1), default=60, help="plan: poses planned (and drawn at random) per variant")
    ap.add_argument("--waypoints", type=at_least(1), default=20, help="plan: the side program's waypoints")
    ap.add_argument("--rows", type=at_least(0), nargs="+", default=[10_000, 30_000, 300_000],
                    help="scale: the synthetic campaigns' sizes (0: none)")
    ap.add_argument("--programs", type=at_least(0), nargs="+", default=[200_000],
                    help="scale: the synthetic programs' waypoints (0: none)")
    ap.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS),
                    help="plan: the variants beside today's project (closed loop)")
    ap.add_argument("--se-check", type=at_least(0), default=5, help="plan: Monte Carlo identifications of the planned "
                                                            "poses' standard errors (first seed; 0 off)")
    ap.add_argument("--curve", action="store_true", help="plan: the learning curve instead of the closed loop")
    ap.add_argument("--sizes", type=at_least(1), nargs="+", default=[25, 50, 100, 200, 400, 700],
                    help="plan --curve: numbers of measured poses")
    ap.add_argument("--extend", action="store_true",
                    help="plan --curve: add --sizes to the curve in plan.json (same seeds, -S, epochs), keeping its runs")
    ap.add_argument("--work", type=at_least(1), default=40, help="plan --curve: the front work region's waypoints")
    ap.add_argument("--keep", default=None, help="plan, scale: keep the scratch projects in this folder")
    ap.add_argument("--station", choices=["new", "same"], default="new",
                    help="plan: measure the new poses from a tracker station of their own (facing the side), "
                         "or from the default campaign's")
    ap.add_argument("--spacings", type=positive, nargs="+", default=list(SPACINGS),
                    help="path: the compensated samples' spacings, mm")
    ap.add_argument("--names", nargs="+", choices=list(PATHS), default=list(PATHS),
                    help="path: the paths to judge")
    a = ap.parse_args(argv)
    if a.seeds and len(set(a.seeds)) != len(a.seeds):   # a repeated seed: a spread of 0 and an ensemble of copies
        ap.error(f"--seeds: distinct seeds, got {a.seeds}")
    if a.what == "export":
        bench_export(a.rounds or 2)
    elif a.what == "path":
        bench_path(a.spacings, a.names)
    elif a.what == "scale":
        bench_scale([n for n in a.rows if n], [n for n in a.programs if n], a.keep)
    elif a.what == "plan":
        bench_plan(a.n, a.seeds or [139, 140, 141], a.waypoints, a.variants, a.curve, a.sizes, a.overrides,
                   a.epochs, a.se_check, a.threads, a.work, a.keep,
                   a.station == "new", a.extend)
    elif a.what == "real":
        bench_real(a.seeds or [139], a.epochs, a.sets, a.other_physics, a.overrides, a.engine, a.address, a.threads, a.dnn)
    elif a.what == "serve" and a.hostile:
        bench_hostile(a.seconds)
    elif a.what == "serve":
        bench_serve(a.clients, a.calls, a.paths)
    elif a.what == "sweep":
        bench_sweep()
    else:
        bench_speed(a.soak, a.rounds or 20, a.only, a.torch_threads)


def main(argv=None):
    """run, with a failed job of a sweep (the others finished, and saved) or a bad setting said in one line."""
    from pipeline.lib.learning.sweep import SweepFailed
    try:
        return run(argv)
    except (SweepFailed, ValueError) as e:
        print(f"python -m pipeline.commands.bench: error: {e}", file=sys.stderr)
        raise SystemExit(1) from None


if __name__ == "__main__":
    main()

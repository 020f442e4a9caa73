"""Command: the benchmarks, one module each, written as JSON under reports/bench/.

    python -m pipeline.commands.bench real|speed|serve|sweep|plan|scale|path|export ...   (__main__.py: the options)

real.py    the pipeline on the real sets and the twin, per training seed   real_data.json
speed.py   training, prediction, compensation and controller-path timings   speed.json
serve.py   the compensation service under load (--hostile: beside hostile clients) serve.json, serve_hostile.json
sweep.py   a reduced ablation, in order against a local Ray                 sweep.json
plan.py    the measurement planner's loop closed on the twin; learning curve plan.json
scale.py   ingest and a program at 10k-300k rows: time and peak memory        scale.json
path.py    a path compensated sample by sample vs its waypoints, on the twin  path.json, path_deviation.png
export.py  each ONNX export of the export stage: seconds per round, nodes   export.json
common.py  what they share: the machine, timing, paths, the prepared points

Its modules import the library and each other, never a stage or another command.
"""

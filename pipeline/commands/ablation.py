"""The paper's ablations (sec. 4.2.3-4.2.4) as opt-in DVC matrix stages, over several seeds.

    python -m pipeline.commands.ablation [--engine ray]   run what changed (dvc repro ablation/dvc.yaml), then summarise
    python -m pipeline.commands.ablation sweep --engine ray [--address HOST:6379]
                                                 every group x seed at once as Ray tasks, then summarise

`ablation/dvc.yaml` holds one matrix stage per group (`python -m pipeline.commands.ablation
group NAME`), each training the group over `ablation.seeds` (lib/learning/sweep.py: in order,
or one Ray task per seed), and a summary stage writing reports/ablation.json and
reports/ablation.md. `sweep` runs every group's seeds as one pool of tasks (the
most parallel, outside DVC) and writes the same files. Plain `dvc repro` never runs it (it reads ./dvc.yaml only).
Each group is the main settings with the changes below; a seed sets both the
weight init and the data order.
"""
import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from pipeline.lib.learning import sweep
from pipeline.lib.learning.ablations import GROUPS, Data, Job, train_one
from pipeline.lib.learning.metrics import seed_std
from pipeline.lib.learning.training import independent_seeds
from pipeline.lib.project.artifacts import (CALIBRATED_GEOMETRY, FRAME_JSON, PARTS_JSON, POINTS_TABLE, REPORTS,
                                            SPLIT_TABLE, TIMINGS)
from pipeline.lib.project.config import for_stage, load_params, logger, read_json, split_timings, write_json
from pipeline.lib.reading.campaigns import file_sha256
from pipeline.lib.reading.prepared import load_prepared
from pipeline.lib.reporting.figures import fig_ablation, save
from pipeline.lib.reporting.paper import PAPER_ABLATION, PAPER_ABLATION_EPOCHS

log = logger(__name__)
OUT = REPORTS / "ablation"
PARAMS = {"group": ("robot", "model", "loss", "train", "ablation", "workspace"),   # ablation/dvc.yaml
          "summary": ()}


INPUTS = (POINTS_TABLE, SPLIT_TABLE, FRAME_JSON, CALIBRATED_GEOMETRY, PARTS_JSON)     # what load_prepared reads


def settings_sha256(params: dict) -> str:
    """What a group's runs depend on besides its own changes (the group stage's params and INPUTS), as one
    hash: the summary puts together only groups run on the same."""
    state = {"params": for_stage(params, PARAMS["group"]), "inputs": {str(f): file_sha256(f) for f in INPUTS}}
    return hashlib.sha256(json.dumps(state, sort_keys=True, default=str).encode()).hexdigest()


def jobs_for(params: dict, groups: list[str]) -> tuple[list[Job], Data]:
    """A Job per (group, seed of `ablation.seeds`), and the Data they train on: the pipeline's aligned
    points and geometries."""
    unknown = [g for g in groups if g not in GROUPS]
    if unknown:
        raise ValueError(f"unknown ablation group(s) {unknown}; use {list(GROUPS)}")
    p = for_stage(params, PARAMS["group"])
    independent_seeds(p["ablation"]["seeds"], p["train"]["members"], "params.yaml ablation.seeds")
    prep = load_prepared(p["robot"])
    return [Job(p, g, s) for g in groups for s in p["ablation"]["seeds"]], Data(prep.points, prep.geometries())


def run_groups(params: dict, groups: list[str], engine: str = "sequential", address: str | None = None,
               threads: int | None = None) -> dict:
    """Every (group, seed) of `ablation.seeds` as one job (lib/learning/sweep.py: in order, or Ray tasks);
    writes reports/ablation/<group>.json per group. threads: torch threads per job (default:
    every core when sequential, 1 on Ray)."""
    jobs, data = jobs_for(params, groups)
    seeds, settings = params["ablation"]["seeds"], settings_sha256(params)
    threads = sweep.threads_per_job(engine, threads)
    try:
        runs, timing = sweep.run(train_one, jobs, engine, address, threads, desc="ablation", shared=data)
        failed = None
    except sweep.SweepFailed as e:            # every other run finished: written below, the failures with them
        runs, timing, failed = e.results, e.timing, e
    errors = {i: err for i, _, err in (failed.failures if failed else [])}
    out = {}
    for k, g in enumerate(groups):
        mine = range(k * len(seeds), (k + 1) * len(seeds))
        rec = {"group": g, "changes": GROUPS[g], "settings_sha256": settings,
               "runs": [runs[i] for i in mine if i not in errors],
               "seconds": sum(timing["job_seconds"][i] or 0.0 for i in mine), "engine": engine,
               "threads_per_job": threads}
        if any(i in errors for i in mine):
            rec["failed"] = [{"seed": jobs[i].seed, "error": errors[i]} for i in mine if i in errors]
        out[g], times = split_timings(rec)
        write_json(OUT / f"{g}.json", out[g])
        write_json(TIMINGS / f"ablation_{g}.json", times)
    log.info("%d runs (%d groups x %d seeds) on %s in %.0f s (%.0f s of training), %d failed", len(jobs),
             len(groups), len(seeds), engine, timing["seconds"], sum(t or 0.0 for t in timing["job_seconds"]),
             len(errors))
    if failed:
        raise failed
    return {"groups": out, "timing": timing}


def summarise() -> dict:
    """reports/ablation.json (the issue's layout), a markdown table beside the paper's numbers
    (reports/ablation.md) and its figure (reports/ablation.png), over the groups run on the settings and
    inputs of the group run last (`settings_sha256`); the others are listed as stale."""
    found = sorted((p for p in (OUT / f"{g}.json" for g in GROUPS) if p.exists()), key=lambda p: p.stat().st_mtime_ns)
    records = {p.stem: read_json(p) for p in found}
    last = records[found[-1].stem].get("settings_sha256") if found else None
    stale = sorted(g for g, r in records.items() if r.get("settings_sha256") != last)
    groups, all_failed = {}, {}
    for g in GROUPS:
        r = records.get(g)
        if r is None or g in stale:
            continue
        if not r["runs"]:                                 # every seed failed: said, as a loser would be
            all_failed[g] = {"changes": r["changes"], "failed": r.get("failed", [])}
            continue
        mae = [run["test"]["3d"]["mae"] for run in r["runs"]]
        groups[g] = {"seeds": [run["seed"] for run in r["runs"]], "n": len(mae), "runs": mae,
                     "test_3d_mae_mean": float(np.mean(mae)), "test_3d_mae_std": seed_std(mae),
                     "test_3d_rmse_mean": float(np.mean([run["test"]["3d"]["rmse"] for run in r["runs"]])),
                     "test_3d_r2_mean": (None if any(run["test"]["3d"]["r2"] is None for run in r["runs"]) else  # 1 point
                                         float(np.mean([run["test"]["3d"]["r2"] for run in r["runs"]]))),
                     "epochs_to_best": [run["epochs_to_best"] for run in r["runs"]],
                     "params": r["runs"][0]["n_params"], "changes": r["changes"],
                     **({"failed": r["failed"]} if r.get("failed") else {}),
                     "paper_test_3d_mae": PAPER_ABLATION.get(g)}
    summary = {"groups": groups, **({"all_seeds_failed": all_failed} if all_failed else {}),
               **({"stale": stale} if stale else {})}
    if stale:
        log.warning("left out, run on other settings or inputs than %s: %s (rerun them: python -m "
                    "pipeline.commands.ablation sweep %s)", found[-1].stem, ", ".join(stale), " ".join(stale))
    write_json(REPORTS / "ablation.json", summary)
    rows = ["| group | changes | seeds | test 3D MAE mm (mean ± std) | paper | epochs to best | paper epochs "
            "| parameters |", "|---|---|---|---|---|---|---|---|"]
    for g, s in groups.items():
        paper = "–" if s["paper_test_3d_mae"] is None else f"{s['paper_test_3d_mae']:.4f}"
        std = "–" if s["test_3d_mae_std"] is None else f"{s['test_3d_mae_std']:.4f}"
        n = f"{s['n']}" + (f" ({len(s['failed'])} failed)" if s.get("failed") else "")
        rows.append(f"| {g} | `{json.dumps(s['changes'])}` | {n} | {s['test_3d_mae_mean']:.4f} ± {std} | {paper} | "
                    f"{round(np.mean(s['epochs_to_best']))} | {PAPER_ABLATION_EPOCHS.get(g, '–')} | "
                    f"{s['params']:,} |")
    for g, f in all_failed.items():
        rows.append(f"| {g} | `{json.dumps(f['changes'])}` | 0 ({len(f['failed'])} failed) | every seed failed | "
                    f"{'–' if PAPER_ABLATION.get(g) is None else f'{PAPER_ABLATION[g]:.4f}'} | – | – | – |")
    if stale:
        rows += ["", f"Left out, run on other settings or inputs than `{found[-1].stem}` (the group run last): "
                 + ", ".join(f"`{g}`" for g in stale) + "."]
    (REPORTS / "ablation.md").write_text("\n".join(rows) + "\n")
    save(fig_ablation(summary), REPORTS / "ablation.png")      # ablation/dvc.yaml's output, groups or none
    log.info("ablation summary over %d groups\n%s", len(groups), "\n".join(rows))
    return summary


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m pipeline.commands.ablation", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", nargs="?", default="all", choices=["all", "group", "sweep", "summary"])
    ap.add_argument("group", nargs="*", help="group name(s) (with `group`; `sweep`: default all)")
    ap.add_argument("--engine", choices=sweep.ENGINES, default=os.environ.get("ABLATION_ENGINE", "sequential"),
                    help="sequential, or ray: one Ray task per (group, seed)")
    ap.add_argument("--address", default=None, help="a Ray cluster's address (default: RAY_ADDRESS, else a "
                                                    "local Ray started here)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads per run (default: all cores "
                                                              "sequential, 1 on Ray)")
    a = ap.parse_args(argv)
    unknown = [g for g in a.group if g not in GROUPS]
    if unknown:
        ap.error(f"unknown ablation group(s) {unknown}; use {list(GROUPS)}")
    if a.threads is not None and a.threads < 1:
        ap.error(f"--threads: an integer >= 1, got {a.threads}")
    if a.what in ("group", "sweep"):          # group: one DVC matrix stage; sweep: every group at once
        try:
            run_groups(load_params(), a.group or list(GROUPS), a.engine, a.address, a.threads)
        except sweep.SweepFailed as e:        # the finished runs are written; the summary says what failed
            if a.what == "sweep":
                summarise()
            print(f"pipeline.commands.ablation: error: {e}", file=sys.stderr)
            sys.exit(1)
        if a.what == "sweep":
            summarise()
    elif a.what == "summary":
        summarise()
    else:                                    # the DVC way: only what changed reruns
        env = {**os.environ, "ABLATION_ENGINE": a.engine}
        t0 = time.perf_counter()
        r = subprocess.run(["dvc", "repro", str(Path("ablation") / "dvc.yaml")], env=env)
        log.info("ablation finished in %.0f s", time.perf_counter() - t0)
        sys.exit(r.returncode)


if __name__ == "__main__":
    main()

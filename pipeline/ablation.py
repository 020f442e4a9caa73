"""The paper's ablations (sec. 4.2.3-4.2.4) as opt-in DVC matrix stages, over several seeds.

    python -m pipeline.ablation [-j 2]       run what changed (dvc repro ablation/dvc.yaml), then summarise

`ablation/dvc.yaml` holds one matrix stage per group (`python -m pipeline.ablation
group NAME`), each training the group over `ablation.seeds` with `-j` worker
processes, and a summary stage writing reports/ablation.json and
reports/ablation.md. Plain `dvc repro` never runs it (it reads ./dvc.yaml only).
Each group is the main settings with the changes below; a seed sets both the
weight init and the data order.
"""
import argparse
import copy
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from .lib.artifacts import REPORTS, load_points
from .lib.config import load_params, logger, read_json, section, write_json
from .lib.figures import fig_ablation, save
from .lib.geometry import aligned, physics_geometry
from .lib.metrics import split_metrics
from .lib.paper import PAPER_ABLATION, PAPER_ABLATION_EPOCHS
from .lib.training import predict, train_boter

log = logger(__name__)
OUT = REPORTS / "ablation"
GROUPS = {                                   # name -> params changes (one source of the groups)
    "baseline": {},
    "data_only": {"loss": {"physics": False}},
    "no_mask": {"model": {"mask": "none"}},
    "body_mask": {"model": {"mask": "body"}},
    "no_resnet": {"model": {"head": "linear"}},
    "no_transformer": {"model": {"encoder": False}},
    # not in the paper: SPEC.md's loss-weighting choice, measured the same way
    "paper_weights": {"loss": {"weighting": "paper"}},
    "fixed_weights": {"loss": {"weighting": "fixed"}},
}


def group_params(params: dict, group: str, seed: int) -> dict:
    p = copy.deepcopy(params)
    for name, changes in GROUPS[group].items():
        p[name].update(changes)
    p["model"]["init_seed"], p["train"]["seed"] = seed, seed
    p["train"]["max_epochs"] = params["ablation"]["max_epochs"] or p["train"]["max_epochs"]
    return p


def train_one(args) -> dict:
    """One (group, seed) training run; returns its test metrics and epochs."""
    params, group, seed, threads = args
    import torch
    torch.set_num_threads(threads)
    df = aligned(load_points(), params)
    p = group_params(params, group, seed)
    model, hist = train_boter(p, df, physics_geometry(p, p["model"]["physics"]), progress=False)
    test = split_metrics(df, predict(model.eval(), df))["test"]
    log.info("%s seed %d: test 3D MAE %.4f mm, best epoch %d", group, seed, test["3d"]["mae"],
             hist["best_epoch"])
    return {"seed": seed, "test": test, "epochs_to_best": hist["best_epoch"],
            "epochs_run": hist["epochs_run"], "seconds": hist["seconds"], "n_params": hist["n_params"]}


def run_group(params: dict, group: str, jobs: int) -> dict:
    if group not in GROUPS:
        raise ValueError(f"unknown ablation group {group!r}; use one of {list(GROUPS)}")
    seeds = section(params, "ablation")["seeds"]
    threads = max(1, (os.cpu_count() or 1) // jobs)
    t0 = time.perf_counter()
    tasks = [(params, group, s, threads) for s in seeds]
    if jobs > 1:
        with ProcessPoolExecutor(jobs) as pool:
            runs = list(pool.map(train_one, tasks))
    else:
        runs = [train_one(t) for t in tasks]
    out = {"group": group, "changes": GROUPS[group], "runs": runs, "seconds": time.perf_counter() - t0,
           "jobs": jobs}
    write_json(OUT / f"{group}.json", out)
    return out


def summarise() -> dict:
    """reports/ablation.json (the issue's layout), a markdown table beside the paper's numbers
    (reports/ablation.md) and its figure (reports/ablation.png)."""
    groups = {}
    for g in GROUPS:
        path = OUT / f"{g}.json"
        if not path.exists():
            continue
        r = read_json(path)
        mae = [run["test"]["3d"]["mae"] for run in r["runs"]]
        groups[g] = {"seeds": [run["seed"] for run in r["runs"]], "runs": mae,
                     "test_3d_mae_mean": float(np.mean(mae)), "test_3d_mae_std": float(np.std(mae)),
                     "test_3d_rmse_mean": float(np.mean([run["test"]["3d"]["rmse"] for run in r["runs"]])),
                     "test_3d_r2_mean": float(np.mean([run["test"]["3d"]["r2"] for run in r["runs"]])),
                     "epochs_to_best": [run["epochs_to_best"] for run in r["runs"]],
                     "params": r["runs"][0]["n_params"], "changes": r["changes"],
                     "seconds": r["seconds"], "paper_test_3d_mae": PAPER_ABLATION.get(g)}
    summary = {"groups": groups}
    write_json(REPORTS / "ablation.json", summary)
    rows = ["| group | changes | test 3D MAE mm (mean ± std) | paper | epochs to best | paper epochs "
            "| parameters |", "|---|---|---|---|---|---|---|"]
    for g, s in groups.items():
        paper = "–" if s["paper_test_3d_mae"] is None else f"{s['paper_test_3d_mae']:.4f}"
        rows.append(f"| {g} | `{json.dumps(s['changes'])}` | {s['test_3d_mae_mean']:.4f} ± "
                    f"{s['test_3d_mae_std']:.4f} | {paper} | "
                    f"{int(np.mean(s['epochs_to_best']))} | {PAPER_ABLATION_EPOCHS.get(g, '–')} | "
                    f"{s['params']:,} |")
    (REPORTS / "ablation.md").write_text("\n".join(rows) + "\n")
    if groups:
        save(fig_ablation(summary), REPORTS / "ablation.png")
    log.info("ablation summary over %d groups\n%s", len(groups), "\n".join(rows))
    return summary


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m pipeline.ablation", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", nargs="?", default="all", choices=["all", "group", "summary"])
    ap.add_argument("group", nargs="?", help="group name (with `group`)")
    ap.add_argument("-j", "--jobs", type=int, default=int(os.environ.get("ABLATION_JOBS", 1)),
                    help="worker processes per group (default 1; 2 on a 2-core machine)")
    a = ap.parse_args(argv)
    if a.what == "group":
        run_group(load_params(), a.group, a.jobs)
    elif a.what == "summary":
        summarise()
    else:                                    # the DVC way: only what changed reruns
        env = {**os.environ, "ABLATION_JOBS": str(a.jobs)}
        t0 = time.perf_counter()
        r = subprocess.run(["dvc", "repro", str(Path("ablation") / "dvc.yaml")], env=env)
        log.info("ablation finished in %.0f s", time.perf_counter() - t0)
        sys.exit(r.returncode)


if __name__ == "__main__":
    main()

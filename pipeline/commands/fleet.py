"""Calibrate a fleet: every robot's campaign through the pipeline, in parallel on Ray.

    python -m pipeline.commands.fleet demo [DIR] [--robots 4]     a demo fleet of twins
    python -m pipeline.commands.fleet run data/fleet [--engine ray] [--address HOST:6379] [--out fleet/robots] [--bench]

A fleet is a folder with one folder per robot, each holding its campaign (the
tracker/controller exports) and a `params.yaml` override, like a preset: merged
over the project's params.yaml, paths relative to the robot's folder. Each robot
is one job (lib/learning/sweep.py: in order, or a Ray task on a local instance or a cluster),
which carries the robot's folder as bytes and its merged params: on its node, in a
scratch folder (the robot's files under `campaign/`), the pipeline's stages (ingest ..
evaluate, export, report), each in the job's process (`pipeline.stages.run`, the main that
`dvc repro` runs), its log to `logs/<stage>.log`. The scratch folder comes back as bytes and is written here to `<out>/<robot>/`,
which then holds that robot's params.yaml, campaign, artifacts (models/, data/interim/),
report (reports/index.md) and logs: no filesystem is shared with the nodes; `<out>/<robot>/`
is cleared first, and `--out` may not be the fleet folder or inside it. A robot's params.yaml
is checked before any stage runs (robot_params). A robot that fails is reported with its step
(`params`, a stage, `job`, `write`) and error message (its folder, logs included, still comes
back after a stage's failure), and the others finish. reports/fleet.json and reports/fleet.md:
per robot the test 3D MAE of nominal DH, the classical calibration and the model, written
whatever failed; then the command exits 1 if a robot failed.

DVC: `fleet/dvc.yaml` (opt-in, like ablation/) is one stage whose output is the
per-robot folders: Ray runs the robots in parallel inside it, where a `foreach`
stage per robot would be run by `dvc repro` one at a time. Its deps are the whole
`pipeline/` package (it runs every stage), params.yaml and the fleet folder, so any
change reruns the fleet.
"""
import argparse
import contextlib
import logging
import math
import os
import re
import shutil
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

from pipeline import stages
from pipeline.lib.learning import sweep
from pipeline.lib.project.cli import Refused, one_line
from pipeline.lib.project.config import (LOG_FORMAT, SECTIONS, ParamsError, load_params, logger, read_json, section,
                                           write_json, yaml_text, yaml_values)
from pipeline.lib.reading.campaigns import write_pair
from pipeline.lib.reading.presets import deep_merge
from pipeline.lib.sim.twin import Twin

log = logger(__name__)
CAMPAIGN = "campaign"               # a robot's working folder: its fleet folder's files are copied here
STAGES = ["ingest", "frame", "theory", "split", "calibrate", "parts", "train", "baselines", "evaluate", "export", "report"]
FLEET_JSON, FLEET_MD = Path("reports/fleet.json"), Path("reports/fleet.md")
BENCH_JSON = Path("reports/bench/fleet.json")
DEMO_SEED = 2000
MARKER = ".fleet-output"        # in each robot's output folder: a fleet run wrote it, the next may clear it
TOP_SECTIONS = [s for s in SECTIONS if "." not in s]       # what a robot's params.yaml may name
UNSUPPORTED = [("campaigns", "more", "one campaign per robot: its ingest section's"),   # (section, key, why):
               ("validate", "campaigns", "no validate stage"),                          # given (not empty or
               ("compensate", "drive_check", "no compensate stage")]                    # false), refused


def check_sections(over: dict, path: Path) -> None:
    """A ParamsError naming the robot's params.yaml (path) and the key where `over` names a section the
    project has not (a misspelt one was merged and ignored) or gives a setting the fleet does not run
    (UNSUPPORTED: its paths were never checked either)."""
    unknown = [k for k in over if k not in TOP_SECTIONS]
    if unknown:
        raise ParamsError(f"{path}: unknown section(s) {unknown}: a misspelt one would be ignored. "
                          f"Sections: {', '.join(TOP_SECTIONS)}")
    for name, key, why in UNSUPPORTED:
        given = over.get(name)
        if isinstance(given, dict) and given.get(key):
            raise ParamsError(f"{path}: {name}.{key}: {given[key]!r}: the fleet does not run it ({why})")


def check_merged(p: dict, path: Path) -> None:
    """Every section of the merged params p checked as its stage will (config.section: keys and values),
    before any stage runs; a ParamsError naming the robot's params.yaml (path) and the key."""
    try:
        for name in TOP_SECTIONS:
            if name in p:
                section(p, name)
    except ParamsError as e:
        raise ParamsError(f"{path} (merged over the project's params.yaml): {str(e).removeprefix('params.yaml ')}") \
            from None


def robot_params(base: dict, robot_dir: Path) -> dict:
    """The project's params with the robot's params.yaml merged over it; its campaign paths made
    relative to the robot's working folder, where its folder's files are copied to `campaign/`; no
    further campaigns, no validation campaigns, no twin drive check (the fleet runs no stage that would
    read them). A ValueError naming the file and the key where its params.yaml is no mapping, names a
    section the project has not or a setting the fleet does not run (UNSUPPORTED), a campaign path leaves
    the robot's folder, or the merged params break a section's rules (config.section)."""
    path = robot_dir / "params.yaml"
    over = yaml_values(path.read_text(), str(path)) if path.exists() else {}     # a ParamsError naming file, line
    if not isinstance(over, dict | None) or not isinstance((over or {}).get("ingest", {}), dict):
        raise ValueError(f"{path}: expected a mapping of params.yaml sections (ingest: a mapping too)")
    over = over or {}
    check_sections(over, path)
    p = deep_merge({**base, "campaigns": {**base["campaigns"], "more": {}},
                    "validate": {**base["validate"], "campaigns": {}},
                    "compensate": {**base["compensate"], "drive_check": False}}, over)
    check_merged(p, path)
    for k in ("joints", "tracker"):
        v = p["ingest"][k]
        if not isinstance(v, str) or Path(v).is_absolute() or ".." in Path(v).parts:
            raise ValueError(f"{path}: ingest.{k}: {v!r} is not a path inside the robot's folder")
        p["ingest"][k] = (Path(CAMPAIGN) / v).as_posix()
    return p


def robot_job(base: dict, robot_dir: Path) -> dict:
    """One robot as a job that carries all it needs, so its node shares no filesystem with this one:
    its name, its params (robot_params) and its folder's files as bytes (lib/learning/sweep.py: pack)."""
    return {"robot": robot_dir.name, "params": robot_params(base, robot_dir), "files": sweep.pack(robot_dir)}


def scratch_prefix(name: str) -> str:
    """The prefix of a robot's scratch folder: its name's first 40 characters, those a file name may not
    hold (or a shell would quote) as `_`: any folder name fits (a 250-character one did not: OSError)."""
    return "fleet-" + re.sub(r"[^A-Za-z0-9_.-]", "_", name[:40]) + "-"


def calibrate_robot(job: dict) -> dict:
    """One robot: its folder's files unpacked to `campaign/` of a scratch folder, every stage run there
    (run_logged: in this process, with the code it runs: on Ray, the package shipped with the task; the
    job's torch threads), and the whole folder (params, campaign, models, tables, reports, logs) returned
    as bytes under "files", for the driver to write where it wants it."""
    name, params = job["robot"], job["params"]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix=scratch_prefix(name)) as tmp:
        out = sweep.unpack(job["files"], Path(tmp) / CAMPAIGN).parent
        (out / "params.yaml").write_text(yaml_text(params))
        (out / "logs").mkdir()
        result = None
        for stage in STAGES:
            reason = run_logged(stage, out)
            if reason is not None:
                result = {"robot": name, "status": "failed", "stage": stage, "reason": reason}
                break
        if result is None:
            m = read_json(out / "reports/metrics.json")
            test = lambda method: m["baselines"][method]["test"]["3d"]["mae"]
            result = {"robot": name, "status": "ok", "model": params["robot"]["model"],
                      "n_points": read_json(out / "reports/theory.json")["n_points"],
                      "test_3d_mae_mm": {"nominal": test("nominal_dh"), "calibrated": test("calibrated_dh"),
                                         "model": m["test"]["3d"]["mae"]}}
        result["seconds"] = time.perf_counter() - t0
        result["files"] = sweep.pack(out)
    return result


class InFolder(logging.Formatter):
    """A stage's log lines as `dvc repro` gives them in the project: paths under root (a robot's scratch
    folder, gone when its log is read) named from root."""
    def __init__(self, root: Path):
        super().__init__(*LOG_FORMAT)
        self.prefix = f"{root}{os.sep}"

    def format(self, record) -> str:
        return super().format(record).replace(self.prefix, "")


def run_logged(stage: str, root: Path) -> str | None:
    """Stage `stage` in this process on the project at root, what it logs (InFolder) and prints written to
    root/logs/<stage>.log only. None, or why it failed in one line: bad input as the stage's command
    says it (`pipeline.stages.<stage>: error: ...`, lib/project/cli.py; its paths relative to root, the
    robot's folder), anything else as its exception's last line, the traceback in the log."""
    top = logging.getLogger()
    with open(root / "logs" / f"{stage}.log", "w") as f, \
            contextlib.redirect_stdout(f), contextlib.redirect_stderr(f):
        handler, in_folder = logging.StreamHandler(f), InFolder(root)
        handler.setFormatter(in_folder)
        kept, top.handlers, level = top.handlers, [handler], top.level
        top.setLevel(logging.INFO)
        try:
            stages.run(stage, root=root)
            return None
        except (ValueError, OSError) as e:              # bad input: IngestError, ParamsError, a file
            said = f"pipeline.stages.{stage}: error: {e}".replace(in_folder.prefix, "")
            print(said, file=f)
            return said.splitlines()[-1]
        except Exception as e:                          # a defect: its traceback for whoever reads the log
            traceback.print_exc(file=f)
            return traceback.format_exception_only(e)[-1].strip()
        finally:
            top.handlers = kept
            top.setLevel(level)
            for lg in logging.Logger.manager.loggerDict.values():   # a library's own handler made on the
                if isinstance(lg, logging.Logger):                 # stderr of the moment (dvclive's, on
                    lg.handlers = [h for h in lg.handlers if getattr(h, "stream", None) is not f]   # import)


def md_cell(text: str) -> str:
    """text for a cell of a Markdown table: its `|` escaped (a robot folder's name may hold one)."""
    return text.replace("|", "\\|")


def fleet_estimate(summary: dict, threads: int, robots: int = 100, nodes=(1, 4, 10, 25)) -> dict:
    """A paper estimate of a `robots`-robot fleet's wall time on N nodes like this machine, from the
    measured per-robot time: ceil(robots / (N * slots)) * robot seconds, slots = cores / threads
    (Ray's ~7 s start-up and ms per task left out)."""
    slots = max(1, (os.cpu_count() or 1) // threads)
    per = summary["robot_seconds_mean"]
    return {"measured": {k: summary[k] for k in ("engine", "n_robots", "n_ok", "seconds", "robot_seconds_mean")},
            "threads_per_robot": threads, "slots_per_node": slots,
            "estimate": {f"{robots}_robots_on_{n}_nodes_h": math.ceil(robots / (n * slots)) * per / 3600
                         for n in nodes},
            "assumes": "nodes like this one (cores, speed); each robot's campaign like the demo's"}


def check_out(out: Path, fleet_dir: Path, robots: list[Path]) -> None:
    """A ValueError naming both where `out` is the fleet folder or inside it (each run would add its
    outputs to the robots' folders, and a robot's params.yaml be overwritten by its merged one), or
    where a robot's output folder would hold the fleet folder (clearing it would delete the fleet)."""
    o, f = out.resolve(), fleet_dir.resolve()
    if o == f or f in o.parents:
        raise ValueError(f"--out {out} is the fleet folder {fleet_dir} or inside it: give a folder of its own")
    for d in robots:
        mine, src = o / d.name, d.resolve()
        if mine == f or mine in f.parents or mine == src or mine in src.parents or src in mine.parents:
            raise ValueError(f"--out {out}: robot {d.name}'s output folder {out / d.name} would hold the fleet "
                             f"folder {fleet_dir} or robot {d.name}'s own files: give a folder of its own")


def ours(folder: Path) -> bool:
    """folder is absent, or a fleet run wrote it (its MARKER): one that may be cleared."""
    return not (folder.exists() or folder.is_symlink()) or (
        folder.is_dir() and not folder.is_symlink() and (folder / MARKER).is_file())


def clear(folder: Path) -> None:
    """A robot's output folder gone, so what its run writes there is all it holds; only one a fleet run wrote
    (`ours`): anything else a ValueError naming it, nothing deleted (a review: `--out .` with a robot named
    `data` deleted the project's data/)."""
    if not ours(folder):
        raise ValueError(f"{folder}: not a fleet's output folder (no {MARKER}): nothing cleared or written; "
                         "move it, or give --out a folder of its own")
    if folder.exists():
        shutil.rmtree(folder)


def write_robot(r: dict, out: Path) -> None:
    """A robot's folder, come back in its result, written to out/<robot> (cleared first); a failure to
    write it makes the robot failed (stage `write`), its earlier failure, if any, kept in the reason."""
    files, target = r.pop("files"), out / r["robot"]
    try:
        clear(target)
        sweep.unpack(files, target)
        target.mkdir(parents=True, exist_ok=True)           # (a job that came back with no files)
        (target / MARKER).write_text("written by python -m pipeline.commands.fleet run: cleared by its next run\n")
    except (OSError, ValueError) as e:
        before = f"; before that: {r['stage']}: {r['reason']}" if r["status"] != "ok" else ""
        r.update(status="failed", stage="write", reason=f"{target}: {e}{before}")


def run_jobs(jobs: list, out: Path, engine: str, address: str | None, threads: int) -> tuple[list, dict]:
    """Every robot's job (calibrate_robot) on the engine, each folder written to out as it comes back:
    the robots' results and the timing. A job that raised outside its stages (its scratch folder, its
    files) is that robot's failed row, stage `job`, its error in one line; the others' results stand."""
    if not jobs:
        return [], {"seconds": 0.0, "job_nodes": []}
    try:
        return sweep.run(calibrate_robot, jobs, engine, address, threads, desc="fleet",
                         on_result=lambda i, r: write_robot(r, out))
    except sweep.SweepFailed as e:
        results = list(e.results)
        for i, job, said in e.failures:
            results[i] = {"robot": job["robot"], "status": "failed", "stage": "job", "reason": said,
                          "seconds": e.timing["job_seconds"][i] or 0.0}
        return results, e.timing


def fleet_table(results: list) -> list[str]:
    """The rows of reports/fleet.md: per robot its status (or where and why it failed), the test 3D MAE
    of nominal DH, the classical calibration and the model, and its seconds."""
    rows = ["| robot | status | nominal mm | calibrated mm | model mm | seconds |", "|---|---|---|---|---|---|"]
    for r in results:
        e = r.get("test_3d_mae_mm") if r["status"] == "ok" else None
        said = r["status"] if e else f"failed in {r['stage']}: {r['reason']}"
        rows.append(f"| {md_cell(r['robot'])} | {md_cell(said)} | "
                    + (" | ".join(f"{e[k]:.4f}" for k in ("nominal", "calibrated", "model")) if e else "– | – | –")
                    + f" | {r['seconds']:.0f} |")
    return rows


def run_fleet(fleet_dir, out="fleet/robots", engine: str = "sequential", address: str | None = None,
              threads: int | None = None, base: dict | None = None, bench: bool = False) -> dict:
    """Every robot of the fleet folder calibrated (module doc), each robot's folder written to out/<robot>
    (cleared first, that of a robot that fails too), reports/fleet.json and fleet.md written whatever
    failed: the summary (fleet.json's). A robot that fails is a row of it (`failed`: its stage and reason);
    the caller decides what that means (the command exits 1)."""
    fleet_dir, out = Path(fleet_dir), Path(out)
    robots = sorted(d for d in fleet_dir.iterdir() if d.is_dir() and not d.name.startswith(".")) \
        if fleet_dir.is_dir() else []
    if not robots:
        raise FileNotFoundError(f"{fleet_dir}: no robot folders (one per robot: its campaign and params.yaml)")
    if threads is not None and threads < 1:
        raise ValueError(f"threads: {threads}: torch threads per robot must be >= 1")
    check_out(out, fleet_dir, robots)
    theirs = [str(out / d.name) for d in robots if not ours(out / d.name)]
    if theirs:                                  # said before any robot runs or any folder is cleared
        raise ValueError(f"--out {out}: {', '.join(theirs)} not a fleet's output folder (no {MARKER}): nothing "
                         "cleared or written; move it, or give --out a folder of its own")
    base = base or load_params()
    threads = sweep.threads_per_job(engine, threads)
    jobs, refused = [], []
    for d in robots:
        clear(out / d.name)                     # no earlier run's models or reports under a robot that fails
        try:
            jobs.append(robot_job(base, d))
        except ValueError as e:                 # its params.yaml: that robot fails, the others run
            refused.append({"robot": d.name, "status": "failed", "stage": "params", "reason": str(e), "seconds": 0.0})
    results, timing = run_jobs(jobs, out, engine, address, threads)
    nodes = {j["robot"]: n for j, n in zip(jobs, timing["job_nodes"])}
    results = sorted(results + refused, key=lambda r: r["robot"])
    ok = [r for r in results if r["status"] == "ok"]
    summary = {"fleet": str(fleet_dir), "out": str(out), "engine": engine, "n_robots": len(results),
               "n_ok": len(ok), "failed": {r["robot"]: f"{r['stage']}: {r['reason']}" for r in results
                                          if r["status"] != "ok"},
               "robots": results, "seconds": timing["seconds"], "nodes": nodes,
               "robot_seconds_mean": float(np.mean([r["seconds"] for r in ok])) if ok else None}
    write_json(FLEET_JSON, summary)
    if bench and ok:
        write_json(BENCH_JSON, fleet_estimate(summary, threads))
    rows = fleet_table(results)
    FLEET_MD.write_text("# Fleet calibration (test 3D MAE)\n\n" + "\n".join(rows) + "\n")
    log.info("fleet of %d robots on %s in %.0f s: %d calibrated, %d failed %s\n%s", len(results), engine,
             timing["seconds"], len(ok), len(results) - len(ok), summary["failed"], "\n".join(rows))
    return summary


def demo(fleet_dir="data/fleet", robots: int = 4, n: int = 300, models=("ur5", "ur10")) -> list[Path]:
    """A demo fleet of twins, each its own error seed DEMO_SEED + k, the arm models taken in turn,
    n poses each."""
    out = []
    for k in range(robots):
        model = models[k % len(models)]
        d = Path(fleet_dir) / f"{model}_{k + 1:02d}"
        joints, tracker, _ = Twin(DEMO_SEED + k, robot=model).campaign(n)
        write_pair(d, joints, tracker)
        (d / "params.yaml").write_text(f"# twin seed {DEMO_SEED + k}: a demo {model.upper()} of the fleet\n"
                                       f"robot: {{model: {model}}}\n"
                                       "ingest: {joints: joints.csv, tracker: tracker.csv}\n")
        out.append(d)
    log.info("demo fleet: %d twins (%s, seeds %d..%d), %d poses each, in %s", robots, "/".join(models),
             DEMO_SEED, DEMO_SEED + robots - 1, n, fleet_dir)
    return out


def at_least_one(what: str):
    """An argparse type: an integer >= 1, said where it is not (`--threads -1`: torch refused it in every robot's
    job; `demo --robots 0` wrote nothing, silently)."""
    def parse(text: str) -> int:
        n = int(text)
        if n < 1:
            raise argparse.ArgumentTypeError(f"{text}: {what} must be >= 1")
        return n
    return parse


def main(argv=None):
    return one_line("pipeline.commands.fleet", run, argv)


def run(argv=None):
    ap = argparse.ArgumentParser(prog="python -m pipeline.commands.fleet", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["run", "demo"])
    ap.add_argument("fleet", nargs="?", default="data/fleet", help="the fleet folder (one folder per robot)")
    ap.add_argument("--out", default="fleet/robots", help="where each robot's folder is written (run)")
    ap.add_argument("--engine", choices=sweep.ENGINES, default="ray")
    ap.add_argument("--address", default=None, help="a Ray cluster (default: RAY_ADDRESS, else local)")
    ap.add_argument("--threads", type=at_least_one("torch threads per robot"), default=None,
                    help="torch threads per robot (default: 1 on Ray)")
    ap.add_argument("--robots", type=at_least_one("a demo fleet's robots"), default=4, help="demo: how many twins")
    ap.add_argument("--bench", action="store_true", help="also write reports/bench/fleet.json: the measured "
                                                         "per-robot time and a 100-robot estimate")
    a = ap.parse_args(argv)
    if a.what == "demo":
        demo(a.fleet, a.robots)
    else:
        summary = run_fleet(a.fleet, a.out, a.engine, a.address, a.threads, bench=a.bench)
        failed = [f"{r['robot']} in {r['stage']}" for r in summary["robots"] if r["status"] != "ok"]
        if failed:                              # the reports are written; the run (and a dvc repro) is no success
            raise Refused(f"{len(failed)} of {summary['n_robots']} robot(s) failed ({', '.join(failed)}), "
                          f"{summary['n_ok']} calibrated: the reasons in {FLEET_JSON} and {FLEET_MD}")

if __name__ == "__main__":
    main()

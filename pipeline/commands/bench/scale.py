"""`bench scale`: the ingest stage on large campaigns (10k, 30k, 300k rows) and the program compensator on
a long program (200k waypoints): wall time and peak RSS of each, every run in a process of its own. Writes
reports/bench/scale.json. Needs a finished `dvc repro` in the project (the program run reads the trained
model; the campaigns' poses come from data/raw/joints.csv).

The campaigns are synthetic: poses near the bundled campaign's, positions from nominal FK (the robot and
tool of params.yaml) in a tracker frame, 0.03 mm noise, and one gross misread (+200 mm) per 1000 points;
the program's waypoints lie near the bundled poses (targets: their nominal positions)."""
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.commands.bench.common import BENCH, ROOT, machine
from pipeline.lib.project.columns import JOINTS_DEG
from pipeline.lib.project.config import load_params, logger, read_json, write_json, yaml_text
from pipeline.lib.robot.kinematics import fk_numpy
from pipeline.lib.robot.robots import load_robot

log = logger(__name__)
POSES = ROOT / "data" / "raw" / "joints.csv"
MISREAD_EVERY, MISREAD_MM = 1000, 200.0


def near_poses(n: int, rng: np.random.Generator, robot, spread_deg: float) -> np.ndarray:
    """(n, 6) deg: bundled poses drawn at random, each joint moved by N(0, spread_deg), within the limits."""
    base = pd.read_csv(POSES)[JOINTS_DEG].to_numpy()
    q = base[rng.integers(0, len(base), n)] + rng.normal(0.0, spread_deg, (n, 6))
    return np.clip(q, robot.limits_deg[:, 0] + 1e-3, robot.limits_deg[:, 1] - 1e-3)


def write_campaign(folder, n: int, robot, seed: int = 0) -> tuple[str, str]:
    """joints.csv and tracker.csv of n synthetic points in `folder` (see the module docstring)."""
    rng = np.random.default_rng(seed)
    q = near_poses(n, rng, robot, 2.0)
    angle = np.radians(30.0)
    R = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    m = fk_numpy(q, robot) @ R.T + [-1500.0, 1800.0, 2100.0] + rng.normal(0.0, 0.03, (n, 3))
    m[::MISREAD_EVERY, 1] += MISREAD_MM
    ids = np.char.add("P", np.char.zfill(np.arange(1, n + 1).astype(str), 7))
    folder = Path(folder)
    joints, tracker = folder / "joints.csv", folder / "tracker.csv"
    pd.DataFrame({"point_id": ids, **dict(zip(JOINTS_DEG, q.T))}).to_csv(joints, index=False, float_format="%.6f")
    pd.DataFrame({"Name": ids, "X": m[:, 0], "Y": m[:, 1], "Z": m[:, 2]}).to_csv(tracker, index=False,
                                                                                 float_format="%.4f")
    return str(joints), str(tracker)


def write_program(path, n: int, robot, seed: int = 0) -> str:
    """A waypoints file of n waypoints near the bundled poses (no target columns)."""
    q = near_poses(n, np.random.default_rng(seed), robot, 0.5)
    ids = np.char.add("W", np.char.zfill(np.arange(1, n + 1).astype(str), 7))
    pd.DataFrame({"point_id": ids, **dict(zip(JOINTS_DEG, q.T))}).to_csv(path, index=False, float_format="%.6f")
    return str(path)


def peak_rss_mb(pid: int) -> float | None:
    """A running process's peak resident set so far (VmHWM, MB), None once it is gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    kb = next((int(l.split()[1]) for l in status.splitlines() if l.startswith("VmHWM:")), None)
    return None if kb is None else kb / 1024


def measured(argv: list, cwd, log_path) -> dict:
    """Run argv in a process of its own -> {seconds, peak_rss_mb (its VmHWM, read every 20 ms: its own,
    whatever this process holds), returncode, load (the 1-minute load average before and after: other
    work on the machine slows it), log (its last lines)}."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "DVC_NO_ANALYTICS": "1"}
    load, peak = os.getloadavg()[0], 0.0
    with open(log_path, "w") as out:
        t0 = time.perf_counter()
        p = subprocess.Popen(argv, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT)
        while p.poll() is None:
            peak = max(peak, peak_rss_mb(p.pid) or 0.0)
            time.sleep(0.02)
        seconds = time.perf_counter() - t0
    tail = Path(log_path).read_text().splitlines()[-6:]
    return {"seconds": round(seconds, 2), "peak_rss_mb": round(peak, 1), "returncode": p.returncode,
            "load": [round(load, 2), round(os.getloadavg()[0], 2)], "log": tail}


def bench_ingest(n: int, params: dict, tmp: Path) -> dict:
    """The ingest stage (`python -m pipeline.stages.ingest`) on a synthetic campaign of n points, in a scratch
    project whose params.yaml names it."""
    folder = tmp / f"ingest_{n}"
    folder.mkdir()
    robot = load_robot(params["robot"])
    joints, tracker = write_campaign(folder, n, robot)
    p = {**params, "ingest": {**params["ingest"], "joints": joints, "tracker": tracker,   # positions only
                              "columns": {**params["ingest"]["columns"], "orientation": None}},
         "campaigns": {**params["campaigns"], "more": {}}}
    (folder / "params.yaml").write_text(yaml_text(p))
    run = measured([sys.executable, "-m", "pipeline.stages.ingest"], folder, folder / "log.txt")
    report = folder / "reports" / "ingest.json"
    if report.exists():
        s = read_json(report)
        run.update(n_kept=s["n_kept"], dropped_counts=s["dropped_counts"], gross_outlier=s["gross_outlier"])
    return {"rows": n, **run}


def bench_program(n: int, params: dict, tmp: Path) -> dict:
    """`python -m pipeline.commands.program` on a synthetic program of n waypoints, with the project's trained model."""
    src = write_program(tmp / f"program_{n}.csv", n, load_robot(params["robot"]))
    run = measured([sys.executable, "-m", "pipeline.commands.program", src, "--out", str(tmp / "program_comp.csv"),
                    "--urscript", str(tmp / "program_comp.script"), "--comment-out-unreached"],
                   ROOT, tmp / f"program_{n}.log")
    return {"waypoints": n, **run}


def bench_scale(ingest_rows=(10_000, 30_000, 300_000), program_waypoints=(200_000,), keep=None) -> dict:
    """Each ingest size and each program length, in a process of its own (scratch files in a temporary
    folder, under `keep` if given); writes reports/bench/scale.json."""
    params = load_params()
    out = {"machine": machine(), "what": "wall time and peak RSS of the ingest stage on synthetic campaigns "
                                         "and of the program compensator on synthetic programs",
           "ingest": [], "program": []}
    with tempfile.TemporaryDirectory(dir=keep) as tmp:
        tmp = Path(tmp)
        for n in ingest_rows:
            out["ingest"].append(r := bench_ingest(n, params, tmp))
            log.info("ingest %d rows: %.1f s, peak %.0f MB (exit %d)", n, r["seconds"], r["peak_rss_mb"],
                     r["returncode"])
        for n in program_waypoints:
            out["program"].append(r := bench_program(n, params, tmp))
            log.info("program %d waypoints: %.1f s, peak %.0f MB (exit %d)", n, r["seconds"], r["peak_rss_mb"],
                     r["returncode"])
    BENCH.mkdir(parents=True, exist_ok=True)
    write_json(BENCH / "scale.json", out)
    return out

"""--project DIR (issue 35): program, path, plan and serve read the project they are named, from any working
directory, and give what they give when run inside it; without it, in a folder that is not a project, they
say what is missing."""
import threading
import xmlrpc.client

import numpy as np
import pandas as pd
import torch

from conftest import exit_code
from pipeline.commands import path as path_command
from pipeline.commands import plan as plan_command
from pipeline.commands import program
from pipeline.commands.serve import make_server, url
from pipeline.lib.project.artifacts import PARAMS_FILE
from pipeline.lib.project.columns import JOINTS_DEG, TARGET
from pipeline.lib.project.config import load_params
from pipeline.lib.sim.twin import sample_poses

SEAM_START = [2.5, -60.4, 91.1, -182.3, -61.2, -100.7]           # as tests/test_path.py's seam
SEAM = [[-650.0, -200.0, 250.0], [-650.0, -100.0, 250.0]]


def outputs(run, inputs, out, project=None) -> list[bytes]:
    """The bytes of every file command `run` writes into folder `out` (made here), given --project or not;
    where they name that folder (plan.json), as OUT."""
    out.mkdir()
    run(inputs(out) + (["--project", str(project)] if project else []))
    return [f.read_bytes().replace(str(out).encode(), b"OUT") for f in sorted(out.rglob("*")) if f.is_file()]


def test_the_commands_read_the_project_they_are_named_from_anywhere(trained_project, tmp_path, monkeypatch,
                                                                    capsys):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    example = trained_project / "data/examples/waypoints.csv"
    seam = tmp_path / "seam.csv"
    pd.DataFrame(SEAM, columns=TARGET).to_csv(seam, index=False)
    side = tmp_path / "side.csv"
    pd.DataFrame(sample_poses(3, np.random.default_rng(11), region="side"), columns=JOINTS_DEG).to_csv(side, index=False)
    commands = {
        "program": (program.run, lambda o: [str(example), "--out", str(o / "c.csv"), "--urscript", str(o / "c.script")]),
        "path": (path_command.run, lambda o: [str(seam), "--out", str(o), "--start-deg", *map(str, SEAM_START)]),
        "plan": (plan_command.run, lambda o: [str(side), "--n", "3", "--out", str(o),
                                              "--tracker-mm", "-1200", "-2600", "900"]),
    }
    for name, (run, inputs) in commands.items():
        monkeypatch.chdir(elsewhere)
        named = outputs(run, inputs, tmp_path / f"{name}_named", trained_project)
        monkeypatch.chdir(trained_project)
        inside = outputs(run, inputs, tmp_path / f"{name}_inside")
        assert named and named == inside, name

    monkeypatch.chdir(elsewhere)
    code, said = exit_code(program.main, [str(example), "--out", str(tmp_path / "x.csv")], capsys)
    assert code == 2 and "params.yaml" in said and not (tmp_path / "x.csv").exists(), said
    assert not any(elsewhere.iterdir())                            # nothing landed in the working directory

    threads = torch.get_num_threads()                             # make_server sets it process-wide
    server = make_server(load_params(trained_project / PARAMS_FILE), "127.0.0.1", 0, root=trained_project)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        q0 = np.radians(SEAM_START)
        client = xmlrpc.client.ServerProxy(url(server))
        r = client.compensate(q0.tolist(), [-650.0, -150.0, 250.0])
        assert r["converged"] and r["residual_mm"] < 1e-3, r
    finally:
        server.shutdown()
        server.server_close()
        torch.set_num_threads(threads)


STAGES_ELSEWHERE = {"ingest": ["data/interim/ingest.parquet", "reports/ingest.json"],
                    "frame": ["reports/frame.json"],
                    "theory": ["data/interim/points.parquet", "reports/theory.json"],
                    "split": ["data/interim/split.parquet", "reports/split.json"]}


def test_a_stage_run_on_a_project_elsewhere_writes_what_it_writes_in_place(trained_project, tmp_path, monkeypatch):
    """pipeline.stages.run(name, root=DIR), as a fleet's robot (a scratch folder) and the benchmarks run the
    stages: the bytes `dvc repro` wrote in place. Before, ingest.json named the files as this process opened
    them, DIR's absolute path: a fleet robot's report named a scratch folder gone when it was read, and its
    bytes changed from run to run (a review found it). A campaign with a bad cell, so the dropped rows'
    `file` and the partner row's detail, which names the other file, are checked too."""
    import shutil
    from pipeline import stages
    copy = tmp_path / "elsewhere"
    for f in [PARAMS_FILE, "data/raw/joints.csv", "data/raw/tracker.csv"]:
        (copy / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(trained_project / f, copy / f)
    tracker = copy / "data/raw/tracker.csv"
    lines = tracker.read_text().splitlines(keepends=True)
    lines[3] = lines[3].replace(",", ",x", 1)                       # a word in a cell: non_numeric
    tracker.write_text("".join(lines))
    shutil.copytree(copy, tmp_path / "in_place")                    # the same campaign, run where it lies
    for name, files in STAGES_ELSEWHERE.items():
        stages.run(name, root=copy)
    ingest = (copy / "reports/ingest.json").read_text()
    assert str(copy) not in ingest and '"file": "data/raw/tracker.csv"' in ingest
    assert '"path": "data/raw/joints.csv"' in ingest
    monkeypatch.chdir(tmp_path / "in_place")                        # dvc repro's way: the stage in the project
    for name in STAGES_ELSEWHERE:
        stages.run(name)
    for files in STAGES_ELSEWHERE.values():
        for f in files:
            assert (copy / f).read_bytes() == (tmp_path / "in_place" / f).read_bytes(), f

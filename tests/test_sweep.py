"""Sweeps on Ray: the same numbers as the sequential path (lib/learning/sweep.py, pipeline.commands.ablation), on a local
Ray and on a two-node cluster that shares nothing of the project with the jobs: the code travels in
Ray's runtime environment, the tables in the object store, folders as bytes."""
import json
import shutil
from pathlib import Path

import pytest

from pipeline.commands import ablation, fleet
from pipeline.commands.bench.real import localized
from pipeline.lib.learning import sweep
from pipeline.lib.project.config import load_params

FILES = ["data/interim/points.parquet", "data/interim/split.parquet", "reports/frame.json",
         "models/calibration.json", "models/parts.json"]


def square(x):
    return x * x


def scaled(x, shared):
    return x * shared["k"]


def test_shared_values_and_folders_as_values(tmp_path):
    """shared reaches every job; a folder packs to {relative path: bytes} and unpacks the same;
    unpack writes nothing outside its folder."""
    out, timing = sweep.run(scaled, [1, 2, 3], shared={"k": 10})
    assert out == [10, 20, 30] and timing["job_nodes"] == [None] * 3
    assert timing["job_code"] == [str(sweep.CODE_ROOT)] * 3
    (tmp_path / "a/b").mkdir(parents=True)
    (tmp_path / "a/b/c.bin").write_bytes(b"\x00\x01")
    (tmp_path / "a/d.txt").write_text("d")
    (tmp_path / "a/skip").mkdir()
    (tmp_path / "a/skip/e").write_text("e")
    files = sweep.pack(tmp_path / "a", skip=("skip",))
    assert files == {"b/c.bin": b"\x00\x01", "d.txt": b"d"}
    sweep.unpack(files, tmp_path / "copy")
    assert sweep.pack(tmp_path / "copy") == files
    with pytest.raises(ValueError, match="not a path inside the folder"):
        sweep.unpack({"../evil": b""}, tmp_path / "copy")
    env = sweep.runtime_env()                       # the package's code, nothing else of the project
    assert env["py_modules"] == [str(sweep.PACKAGE)] and sweep.PACKAGE.name == "pipeline"
    assert "__pycache__/" in env["excludes"]


def test_unknown_engine_and_group_are_named():
    with pytest.raises(ValueError, match="unknown engine 'dask'"):
        sweep.run(square, [1], "dask")
    with pytest.raises(ValueError, match=r"unknown ablation group\(s\) \['nope'\]"):
        ablation.run_groups(load_params(), ["nope"])


def small_ablation(trained_project, folder, monkeypatch, epochs: int) -> dict:
    """The trained project's inputs (FILES) copied to folder, made the working directory; params for a
    two-seed ablation of a small model trained `epochs` epochs."""
    for f in FILES:
        (folder / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(trained_project / f, folder / f)
    params = load_params(trained_project / "params.yaml")
    params["model"].update(d_model=12, n_head=2, n_layer=1, d_hidden=32)
    params["train"].update(max_epochs=epochs, patience=epochs)
    params["ablation"].update(seeds=[3, 4], max_epochs=None)
    monkeypatch.chdir(folder)
    return params


@pytest.mark.slow
@pytest.mark.xdist_group("serial")   # one Ray at a time (a second ray.init could join the first)
def test_bench_real_seeds_on_ray_equal_sequential():
    """`bench real`'s seed sweep (twin, two seeds, a small model, 3 epochs): each seed a job run in
    process, in order or as a Ray task, the same numbers either way, validation included."""
    from pipeline.commands.bench.real import run_set
    over = ["model.d_model=12", "model.n_head=2", "model.n_layer=1", "model.d_hidden=32", "train.patience=3"]
    out = {e: run_set("twin", [5, 6], 3, False, overrides=over, engine=e, threads=1)
           for e in ("sequential", "ray")}
    seq, ray = out["sequential"], out["ray"]
    assert seq["seeds"] == ray["seeds"] == [5, 6] and ray["engine"] == "ray"
    assert seq["test_3d_mae_runs"] == ray["test_3d_mae_runs"]
    assert seq["test_3d_mae_ensemble"] == ray["test_3d_mae_ensemble"]
    assert seq["validation"]["twin_side"]["mean_3d_mm_runs"] == ray["validation"]["twin_side"]["mean_3d_mm_runs"]
    assert len(set(seq["test_3d_mae_runs"]["spi_boter"])) == 2           # two seeds, two models


@pytest.fixture()
def two_nodes():
    """A Ray cluster of two nodes on this machine (a head and a worker, one CPU each), torn down after."""
    from ray.cluster_utils import Cluster
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "object_store_memory": 100 * 2**20})
    try:
        cluster.add_node(num_cpus=1, object_store_memory=100 * 2**20)
        cluster.wait_for_nodes()
        yield cluster
    finally:
        cluster.shutdown()


@pytest.mark.slow
@pytest.mark.xdist_group("serial")   # one Ray at a time (a second ray.init could join the first)
def test_sweep_and_fleet_on_a_two_node_cluster(trained_project, tmp_path, monkeypatch, two_nodes):
    """Issue 24: a two-run ablation sweep (a group's two seeds) on a two-node cluster (ray.cluster_utils.Cluster,
    the driver connecting by its address), run in a folder that holds nothing of the project: the same numbers
    as the sequential engine (one torch thread each), epoch for epoch, one run on each node, the code imported from the
    package Ray shipped with the tasks, not from the project. Then a two-robot fleet on it, one robot's
    campaign broken (a column the reader needs): it is reported with the stage and the reader's message,
    its folder and logs come back too, and the other (a UR10) is calibrated; each robot's folder goes to
    its task as bytes and comes back as bytes, written here. (This replaced a separate three-robot fleet
    on a local Ray, 100 s of the suite: the same run_fleet code, ray.init without an address; and a two-run
    sweep on a local Ray, 58 s: ray.init without an address is test_bench_real_seeds_on_ray_equal_sequential's.)"""
    params = small_ablation(trained_project, tmp_path, monkeypatch, epochs=3)
    seq = ablation.run_groups(params, ["no_resnet"], "sequential", threads=1)
    seq_runs = json.loads((tmp_path / "reports/ablation/no_resnet.json").read_text())["runs"]
    ray_ = ablation.run_groups(params, ["no_resnet"], "ray", address=two_nodes.address, threads=1)
    ray_runs = json.loads((tmp_path / "reports/ablation/no_resnet.json").read_text())["runs"]
    for r, engine in ((seq, "sequential"), (ray_, "ray")):
        assert r["timing"]["engine"] == engine and len(r["timing"]["job_seconds"]) == 2
    assert [x["seed"] for x in ray_runs] == [3, 4]
    for a, b in zip(seq_runs, ray_runs, strict=True):
        assert a["seed"] == b["seed"] and a["test"] == b["test"] and a["epochs_run"] == b["epochs_run"] == 3
    assert seq_runs[0]["test"] != seq_runs[1]["test"]                      # two seeds, two different models
    nodes = ray_["timing"]["job_nodes"]
    assert set(nodes) == {n.node_id for n in two_nodes.list_all_nodes()}            # one run on each node
    project = Path(__file__).resolve().parents[1]
    for code in ray_["timing"]["job_code"]:                  # the shipped copy of the package, not this tree
        assert Path(code, "pipeline/lib/learning/sweep.py").exists() and Path(code).resolve() != project
    assert seq["timing"]["job_code"] == [str(sweep.CODE_ROOT)] * 2
    # two robots, their folders there and back as bytes; one campaign broken
    robots = fleet.demo("fleet_in", robots=2, n=150)                     # ur5_01, ur10_02
    assert [r.name for r in robots] == ["ur5_01", "ur10_02"]
    broken = robots[0] / "tracker.csv"
    broken.write_text(broken.read_text().replace("X,Y,Z", "X,Y,Q", 1))
    f = fleet.run_fleet("fleet_in", "out", engine="ray", address=two_nodes.address,
                        base=params | {"train": {**params["train"], "max_epochs": 6, "patience": 6}})
    assert f["n_robots"] == 2 and f["n_ok"] == 1 and list(f["failed"]) == ["ur5_01"]
    reason = f["failed"]["ur5_01"]
    assert reason.startswith("ingest: pipeline.stages.ingest: error: campaign/tracker.csv, column 'z':")   # the
    assert "column(s) z" in reason                                    # robot's folder's name, not the scratch one's
    assert "column(s) z" in (tmp_path / "out/ur5_01/logs/ingest.log").read_text()   # its folder came back too
    assert f["nodes"]["ur10_02"] in nodes
    ok = [r for r in f["robots"] if r["status"] == "ok"]
    assert [(r["robot"], r["model"]) for r in ok] == [("ur10_02", "ur10")]
    e = ok[0]["test_3d_mae_mm"]
    assert e["calibrated"] < e["nominal"] / 3                            # the twin really calibrated
    for name in ("campaign/tracker.csv", "params.yaml", "models/boter.pt", "models/model.onnx",
                 "models/calibrated.urdf", "reports/index.md", "logs/train.log"):
        assert (tmp_path / "out/ur10_02" / name).is_file(), name
    assert "joints: campaign/joints.csv" in (tmp_path / "out/ur10_02/params.yaml").read_text()
    logs = {s: (tmp_path / "out/ur10_02/logs" / f"{s}.log").read_text() for s in ("ingest", "train")}
    assert " ingest: wrote data/interim/ingest.parquet (150 rows" in logs["ingest"]      # each stage's own lines
    assert " train: trained SPI-BoTER " in logs["train"] and " ingest: " not in logs["train"]
    assert json.loads((tmp_path / "reports/fleet.json").read_text())["n_ok"] == 1
    assert "failed in ingest" in (tmp_path / "reports/fleet.md").read_text()


def test_localized_inputs_keep_one_table_one_file(tmp_path):
    """bench real's seeds carry their campaigns' inputs (localized): a campaign whose joints and positions
    are one table (ipa-ur10's Series_B) must stay one file, or ingest reads it as two and asks for a point
    id column (the defect: bench real failed on the ipa-ur10 preset's validation campaigns)."""
    src = tmp_path / "src"
    src.mkdir()
    (src / "table.csv").write_text("j1\n1\n")
    (src / "joints.csv").write_text("point_id\nA\n")
    (src / "tracker.csv").write_text("Name\nA\n")
    one, two = str(src / "table.csv"), {"joints": str(src / "joints.csv"), "tracker": str(src / "tracker.csv")}
    params = {"ingest": two, "campaigns": {"more": None},
              "validate": {"campaigns": {"b": {"ingest": {"joints": one, "tracker": one}}}}}
    out = tmp_path / "out"
    p = localized(params, out)
    b = p["validate"]["campaigns"]["b"]["ingest"]
    assert b["joints"] == b["tracker"] and (out / b["joints"]).read_text() == "j1\n1\n"
    assert p["ingest"]["joints"] != p["ingest"]["tracker"]
    assert (out / p["ingest"]["tracker"]).read_text() == "Name\nA\n"
    assert params["validate"]["campaigns"]["b"]["ingest"]["joints"] == one           # the input left as it was


def broken_at_one(x):
    if x == 1:
        raise ValueError("job 1 broke")
    return x * 10


def test_a_failed_job_lets_the_others_finish_and_is_named():
    """Review D: a job that raised stopped the sweep (sequential: the later jobs never ran; Ray: the
    running ones were dropped at shutdown) and every finished result was lost with it. Now every job
    runs, each result reaches on_result, and SweepFailed names the failed job and carries the others."""
    seen = []
    with pytest.raises(sweep.SweepFailed, match=r"1 of 4 job\(s\) failed.*job 1 \(1\): ValueError: job 1 broke") as e:
        sweep.run(broken_at_one, [0, 1, 2, 3], on_result=lambda i, r: seen.append((i, r)))
    assert seen == [(0, 0), (2, 20), (3, 30)]
    assert e.value.results == [0, None, 20, 30] and len(e.value.timing["job_seconds"]) == 4


def test_an_ablation_with_a_failed_run_writes_the_others_and_names_it(tmp_path, monkeypatch):
    """Review D: one (group, seed) that raised lost the whole ablation: nothing written. Now the group's
    file holds the runs that finished and `failed` the seed with its error; the summary says so."""

    def flaky(job, data):
        if job.seed == 4:
            raise ValueError("diverged")
        return {"seed": job.seed, "test": {"3d": {"mae": 0.1 * job.seed, "rmse": 1.0, "r2": 0.5}},
                "epochs_to_best": 1, "epochs_run": 1, "seconds": 0.0, "n_params": 7}
    monkeypatch.setattr(ablation, "jobs_for", lambda params, groups: (
        [ablation.Job({}, g, s) for g in groups for s in (3, 4, 5)], None))
    monkeypatch.setattr(ablation, "train_one", flaky)
    monkeypatch.setattr(ablation, "settings_sha256", lambda params: "the same")
    monkeypatch.setattr(ablation, "OUT", tmp_path / "ablation")
    monkeypatch.setattr(ablation, "TIMINGS", tmp_path / "timings")
    params = {"ablation": {"seeds": [3, 4, 5]}}
    with pytest.raises(sweep.SweepFailed, match=r"baseline seed 4\): ValueError: diverged"):
        ablation.run_groups(params, ["baseline"])
    rec = json.loads((tmp_path / "ablation" / "baseline.json").read_text())
    assert [r["seed"] for r in rec["runs"]] == [3, 5]
    assert rec["failed"] == [{"seed": 4, "error": "ValueError: diverged"}]


def test_a_method_measured_on_one_seed_has_no_spread():
    """A review (2026-12-06): bench real trains the other physics branch on the first seed only, and wrote it as
    mean ± 0.0 beside the others' spread over every seed. One seed now has no std (null), as the records say."""
    from pipeline.commands.bench.real import seed_stats, seed_summary
    s = seed_summary({"spi_boter_calibrated": [0.30, 0.32, 0.31], "spi_boter_nominal": [0.35]}, 0.8, "calibrated")
    assert s["test_3d_mae_std"]["spi_boter"] == pytest.approx(0.0081650, abs=1e-6)      # population std, 3 seeds
    assert s["test_3d_mae_std"]["spi_boter_nominal"] is None and s["test_3d_mae_runs"]["spi_boter_nominal"] == [0.35]
    assert seed_stats([{"a": 1.0}])["a"]["std"] is None


def test_seeds_whose_runs_would_share_members_are_refused():
    """A review (2026-12-06): with train.members 2, ablation seeds 139 and 140 trained members (139, 140) and
    (140, 141): one model, bit for bit, in both runs, so their spread understated the seeds'. Refused now,
    naming the setting, before any data is read."""
    from pipeline.lib.learning.training import independent_seeds
    params = load_params(Path(__file__).resolve().parents[1] / "params.yaml")
    params["train"]["members"], params["ablation"]["seeds"] = 2, [139, 140]
    with pytest.raises(ValueError, match=r"params.yaml ablation.seeds: seeds \[139, 140\] with train.members = 2 "
                                         r"share members"):
        ablation.jobs_for(params, ["baseline"])
    independent_seeds([139, 141, 143], 2, "x")                        # two apart: none shared
    independent_seeds([139, 140], 1, "x")

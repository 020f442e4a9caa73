"""Sweeps on Ray: the same numbers as the sequential path (lib/sweep.py, pipeline.ablation)."""
import json
import shutil

import pytest

from pipeline import ablation
from pipeline.lib import sweep
from pipeline.lib.config import load_params

FILES = ["data/interim/points.parquet", "data/interim/split.parquet", "reports/frame.json",
         "models/calibration.json"]


def square(x):
    return x * x


def test_unknown_engine_and_group_are_named():
    with pytest.raises(ValueError, match="unknown engine 'dask'"):
        sweep.run(square, [1], "dask")
    with pytest.raises(ValueError, match=r"unknown ablation group\(s\) \['nope'\]"):
        ablation.run_groups(load_params(), ["nope"])


@pytest.mark.slow
def test_two_run_sweep_on_ray_equals_sequential(trained_project, tmp_path, monkeypatch):
    """Two training runs (two seeds of one ablation group, a small model) as Ray tasks on a local
    Ray instance and one after the other: identical test metrics, epoch for epoch."""
    for f in FILES:
        (tmp_path / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(trained_project / f, tmp_path / f)
    params = load_params(trained_project / "params.yaml")
    params["model"].update(d_model=12, n_head=2, n_layer=1, d_hidden=32)
    params["train"].update(max_epochs=4, patience=4)
    params["ablation"].update(seeds=[3, 4], max_epochs=None)
    monkeypatch.chdir(tmp_path)
    out = {}
    for engine in ("sequential", "ray"):
        r = ablation.run_groups(params, ["no_resnet"], engine, threads=1)
        assert r["timing"]["engine"] == engine and len(r["timing"]["job_seconds"]) == 2
        out[engine] = json.loads((tmp_path / "reports/ablation/no_resnet.json").read_text())
    seq, ray = out["sequential"]["runs"], out["ray"]["runs"]
    assert [x["seed"] for x in ray] == [3, 4]
    for a, b in zip(seq, ray):
        assert a["test"] == b["test"] and a["epochs_run"] == b["epochs_run"] == 4
    assert seq[0]["test"] != seq[1]["test"]                        # two seeds, two different models


@pytest.mark.slow
def test_bench_real_seeds_on_ray_equal_sequential():
    """`bench real`'s seed sweep (twin, two seeds, a small model, 3 epochs): each seed a job run in
    process, in order or as a Ray task, the same numbers either way, validation included."""
    from pipeline.bench.real import run_set
    over = ["model.d_model=12", "model.n_head=2", "model.n_layer=1", "model.d_hidden=32", "train.patience=3"]
    out = {e: run_set("twin", [5, 6], 3, False, overrides=over, engine=e, threads=1)
           for e in ("sequential", "ray")}
    seq, ray = out["sequential"], out["ray"]
    assert seq["seeds"] == ray["seeds"] == [5, 6] and ray["engine"] == "ray"
    assert seq["test_3d_mae_runs"] == ray["test_3d_mae_runs"]
    assert seq["test_3d_mae_ensemble"] == ray["test_3d_mae_ensemble"]
    assert seq["validation"]["twin_side"]["mean_3d_mm_runs"] == ray["validation"]["twin_side"]["mean_3d_mm_runs"]
    assert len(set(seq["test_3d_mae_runs"]["spi_boter"])) == 2           # two seeds, two models

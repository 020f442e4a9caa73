"""The report stage on small synthetic inputs: every figure, index.md's links, the PLY."""
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from pipeline import report
from pipeline.lib import figures, page
from pipeline.lib.columns import AXES, JOINTS_DEG, MEAS, PRED, THEORY
from pipeline.lib.config import load_params, write_json
from pipeline.lib.kinematics import nominal_geometry
from pipeline.lib.metrics import drive_table, regression_metrics
from pipeline.lib.robots import nominal_robot
from pipeline.lib.training import make_model, save_model
from pipeline.lib.validation import summary

ROOT = Path(__file__).resolve().parents[1]
SMALL_MODEL = {"d_model": 12, "n_head": 2, "n_layer": 2, "d_hidden": 16}
N = 60


def small_params() -> dict:
    """The repo's params.yaml (every key of every section) with a small nominal-physics model."""
    params = load_params(ROOT / "params.yaml")
    params["model"].update(SMALL_MODEL, physics="nominal", encoder=True, mask="spi")
    params["compensate"].update(tol_mm=1e-3, tol_mse=1e-4)
    return params


def write_inputs(root: Path, params: dict, optional: bool = True) -> pd.DataFrame:
    """predictions.parquet + metrics.json (+ frame.json and, if optional, everything else)."""
    rng = np.random.default_rng(0)
    (root / "data/interim").mkdir(parents=True)
    (root / "reports").mkdir()
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    split = np.array(["train"] * 40 + ["val"] * 10 + ["test"] * 10)
    df = pd.DataFrame({"point_id": [f"P{i + 1:04d}" for i in range(N)], "split": split})
    df[JOINTS_DEG] = rng.uniform(-170, 170, (N, 6))
    theory = rng.uniform(-600, 600, (N, 3))
    err = rng.normal(0, 1.0, (N, 3))                       # real error, mm
    df[THEORY], df[MEAS] = theory, theory + err
    df[PRED] = theory + 0.8 * err + rng.normal(0, 0.2, (N, 3))
    df.to_parquet(root / "data/interim/predictions.parquet", index=False)

    def by_split(p):
        return {s: regression_metrics(p[m], df[MEAS].to_numpy()[m], theory[m])
                for s in ("train", "val", "test") if (m := split == s).any()}
    metrics = by_split(df[PRED].to_numpy())
    metrics["baselines"] = {"nominal_dh": by_split(theory), "spi_boter_nominal": by_split(df[PRED].to_numpy()),
                            "dnn": by_split(theory + 0.5 * err)}
    metrics["model"] = "spi_boter_nominal"
    (root / "reports/metrics.json").write_text(json.dumps(metrics))
    frame = {"R": np.eye(3).tolist(), "t": [0.0, 0.0, 0.0], "rms_mm": 1.0, "n_used": N,
             "outliers": ["P0099"], "outlier_residual_mm": {"P0099": 30.0}, "tool_mm": [0.0, 0.0, 0.0]}
    (root / "reports/frame.json").write_text(json.dumps(frame))
    if not optional:
        return df

    (root / "models").mkdir()                              # physics "nominal": geometry from frame.json's tool
    model = make_model(params["model"], nominal_geometry(nominal_robot("ur5")))
    save_model(model, root / "models/boter.pt", params["model"])
    live = root / "reports/live/plots/metrics"
    live.mkdir(parents=True)
    for name, v0 in [("train_mae_3d_mm", 1.5), ("val_mae_3d_mm", 1.6), ("loss", 2.0),
                     ("data_loss", 2.0), ("physics_loss", 1e-6), ("alpha", 0.1)]:
        pd.DataFrame({"step": range(30), name: v0 * np.exp(-np.arange(30) / 15)}).to_csv(
            live / f"{name}.tsv", sep="\t", index=False)
    rows = [{"solver": s, "iteration": i, "max_residual_mm": 0.1 * 0.5 ** i,
             "mean_residual_mm": 0.05 * 0.5 ** i} for s, n in (("adam", 20), ("lm", 3)) for i in range(n)]
    pd.DataFrame(rows).to_csv(root / "reports/compensation_convergence.csv", index=False)
    before, after = rng.normal(0, 1.0, (10, 3)), rng.normal(0, 0.15, (10, 3))
    drive = pd.DataFrame(np.hstack([before, after]),
                         columns=[f"{w}_{a}" for w in ("before", "after") for a in AXES])
    drive.insert(0, "point_id", df.point_id[split == "test"].to_numpy())
    drive.to_csv(root / "reports/drive_check.csv", index=False)
    zero = np.zeros((10, 3))
    comp = {"solver": "lm", "n_points": 10,
            **{s: {"converged_share": 1.0, "iterations_mean": 3.0, "iterations_max": 5,
                   "residual_mm_mean": 1e-4, "residual_mm_max": 5e-4, "seconds": 0.1,
                   "ms_per_point": 10.0} for s in ("adam", "lm")},
            "drive_check": {"before": drive_table(before, zero), "after": drive_table(after, zero),
                            "noise_floor_mm": 0.05}}
    (root / "reports/compensation.json").write_text(json.dumps(comp))
    (root / "reports/ingest.json").write_text(json.dumps(
        {"n_read": {"joints": N + 1, "tracker": N + 1}, "n_kept": N, "dropped_counts": {"duplicate": 1},
         "dropped": [{"point_id": "P0001", "file": "joints.csv", "row": 3, "reason": "duplicate",
                      "detail": "id already used"}]}))
    (root / "reports/baselines.md").write_text("| method (test) | 3D MAE mm |\n|---|---|\n| x | 1.0 |\n")
    inside = np.arange(40) < 25                            # a validation campaign, 15 points outside
    val = pd.DataFrame({"point_id": [f"V{i:04d}" for i in range(40)], "campaign": "moved",
                        "registered": np.arange(40) < 5, "error_nominal_mm": rng.uniform(0.5, 2, 40),
                        "error_calibrated_mm": rng.uniform(0.1, 0.4, 40),
                        "error_calibrated_parts_mm": rng.uniform(0.1, 0.3, 40),
                        "error_model_mm": np.where(inside, 0.1, 0.3), "uncertainty_mm": 0.15,
                        "in_workspace": inside, "in_range_angle_map": True})
    val.to_parquet(root / "reports/validation.parquet", index=False)
    (root / "reports/validation.json").write_text(json.dumps({"campaigns": {"moved": summary(val, "refit")
                                                                            | {"ingest": {"n_kept": 40,
                                                                               "dropped": [], "dropped_counts": {}}}}}))
    return df


def links(index: Path) -> list[str]:
    return re.findall(r"\]\(([^)\s]+)\)", index.read_text())


def assert_png(path: Path):
    from PIL import Image
    with Image.open(path) as im:
        im.verify()
    with Image.open(path) as im:
        w, h = im.size
        assert im.format == "PNG"
    assert 300 <= w <= 3000 and 200 <= h <= 2500, (path, w, h)


ABLATION_LINKS = {"ablation.md", "ablation.json", "ablation.png"}   # opt-in: linked, never read


def test_report_writes_every_figure_index_and_ply(tmp_path, monkeypatch):
    params = small_params()
    monkeypatch.chdir(tmp_path)
    df = write_inputs(tmp_path, params)
    (tmp_path / "reports/ablation.json").write_text("{not json")   # the report must not read it
    out = report.run(params)
    text = (tmp_path / "reports/index.md").read_text()
    assert "### `moved`" in text and "**57% of them lie inside the joint-space coverage" in text
    assert "the model extrapolates" in text

    assert out["figures"] == {name: "ok" for name in figures.FIGURES}
    for name in figures.FIGURES:
        assert_png(tmp_path / "reports/plots" / f"{name}.png")

    index = tmp_path / "reports/index.md"
    targets = links(index)
    for name in figures.FIGURES:
        assert f"plots/{name}.png" in targets
    assert ABLATION_LINKS <= set(targets)
    for t in set(targets) - ABLATION_LINKS:                 # every other link resolves
        assert (index.parent / t).exists(), t
    text = index.read_text()
    assert "0.2515" in text and "0.9479" in text           # the paper's numbers beside ours
    assert "(paper: 0.2515 / 0.2850 / 0.9479)" in text
    assert "Skipped" not in text
    assert "within ±0.5 mm" in text                         # Table 9 layout

    import open3d as o3d
    pc = o3d.io.read_point_cloud(str(tmp_path / "reports/points_error.ply"))
    assert len(pc.points) == len(df)
    assert pc.has_colors() and len(pc.colors) == len(df)
    np.testing.assert_allclose(np.asarray(pc.points), df[MEAS].to_numpy(), atol=1e-9)
    assert np.unique(np.round(np.asarray(pc.colors), 3), axis=0).shape[0] > 5   # a colormap, not one colour


def test_missing_optional_inputs_are_skipped_with_a_note(tmp_path, monkeypatch):
    params = small_params()
    params["model"]["encoder"] = False
    monkeypatch.chdir(tmp_path)
    df = write_inputs(tmp_path, params, optional=False)
    plots = tmp_path / "reports/plots"
    plots.mkdir(parents=True)
    (plots / "drive_check.png").write_bytes(b"stale")      # from an earlier run: must go
    out = report.run(params)

    skipped = {n for n, s in out["figures"].items() if s != "ok"}
    assert skipped == {"training_curves", "attention_maps", "compensation_convergence", "drive_check",
                       "validation"}
    for name in figures.FIGURES:
        assert (plots / f"{name}.png").exists() == (name not in skipped)
    index = tmp_path / "reports/index.md"
    for t in set(links(index)) - ABLATION_LINKS:
        assert (index.parent / t).exists(), t
    text = index.read_text()
    assert text.count("_Skipped:") == len(skipped)
    assert "no trained model" in text and "No drive check" in text      # the checkpoint says encoder or not
    assert "calibration.json not found" in text and "train.json not found" in text
    assert not (tmp_path / "reports/ablation.json").exists()   # no ablation run, yet a full page
    assert "`python -m pipeline.ablation` (`--engine ray` in parallel)" in text
    import open3d as o3d
    assert len(o3d.io.read_point_cloud(str(tmp_path / "reports/points_error.ply")).points) == len(df)


def test_page_sections_take_the_loaded_summaries():
    assert "not found" in page.section_calibration(None) and "not found" in page.section_training(None)
    c = {"identified": ["d1", "a2"], "n_candidates": 40, "rank": 2, "fixed": {"d6": "unidentifiable"},
         "condition_number": 12.5, "residual_sigma_mm": 0.05, "loss": "soft_l1", "loss_scale_mm": 0.5,
         "nfev": 9, "estimates": {"d1": {"delta": 0.3, "se": 0.01, "unit": "mm"}}}
    text = page.section_calibration(c)
    assert "2 of 40 parameters identified" in text and "d6 (unidentifiable)" in text
    tr = {"n_params": 1234, "n_train": 40, "n_val": 10, "best_val_mae_3d_mm": 0.3, "best_epoch": 7,
          "epochs_run": 20, "seconds": 1.0, "seconds_per_epoch": 0.05, "alpha": 0.1,
          "loss_weights": [1.0, 1.0]}
    assert "1234 parameters" in page.section_training(tr) and "epoch 7 of 20" in page.section_training(tr)


def test_ablation_summary_writes_table_with_paper_epochs_and_figure(tmp_path, monkeypatch):
    from pipeline import ablation
    monkeypatch.chdir(tmp_path)
    for g, mae in (("baseline", 0.25), ("no_mask", 0.28), ("paper_weights", 0.26)):
        runs = [{"seed": s, "test": {"3d": {"mae": mae + 0.01 * k, "rmse": 0.3, "r2": 0.9}},
                 "epochs_to_best": 100 + k, "n_params": 5000} for k, s in enumerate((1, 2))]
        write_json(tmp_path / "reports/ablation" / f"{g}.json",
                            {"group": g, "changes": ablation.GROUPS[g], "runs": runs, "seconds": 1.0})
    summary = ablation.summarise()
    assert set(summary["groups"]) == {"baseline", "no_mask", "paper_weights"}
    md = (tmp_path / "reports/ablation.md").read_text().splitlines()
    assert "| paper epochs |" in md[0]
    rows = {r.split("|")[1].strip(): [c.strip() for c in r.split("|")[1:-1]] for r in md[2:]}
    col = md[0].split("|")[1:-1].index(" paper epochs ")
    assert rows["no_mask"][col] == "402" and rows["baseline"][col] == "111"
    assert rows["paper_weights"][col] == "–"                 # not in the paper
    assert_png(tmp_path / "reports/ablation.png")
    assert json.loads((tmp_path / "reports/ablation.json").read_text()) == summary


def test_scatter_r2_is_the_metrics_r2():
    rng = np.random.default_rng(1)
    theory = rng.normal(0, 100, (50, 3))
    real = theory + rng.normal(0, 1, (50, 3))
    pred = theory + 0.7 * (real - theory) + rng.normal(0, 0.1, (50, 3))
    m = regression_metrics(pred, real, theory)
    for k, a in enumerate(AXES):
        assert figures.r2((real - theory)[:, k], (pred - theory)[:, k]) == pytest.approx(m[a]["r2"])


def test_figures_are_one_registry_with_captions():
    assert "ablation" not in figures.FIGURES                 # drawn by pipeline.ablation, not the report
    for name, fn in figures.FIGURES.items():
        assert re.fullmatch(r"[a-z0-9_]+", name)
        assert len(figures.caption(fn)) > 20, name
    assert len(figures.caption(figures.fig_ablation)) > 20

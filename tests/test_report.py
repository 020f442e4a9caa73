"""The report stage on small synthetic inputs: every figure, index.md's links, the PLY; the customer's
summary page on the project's own artifacts."""
import json
import re
import shutil
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from pipeline.lib.learning.checkpoint import make_model, save_model
from pipeline.lib.learning.metrics import drive_table, regression_metrics
from pipeline.lib.learning.validation import summary
from pipeline.lib.project.columns import AXES, JOINTS_DEG, MEAS, PRED, THEORY
from pipeline.lib.project.config import for_stage, load_params, read_json, write_json
from pipeline.lib.reporting import figures, page
from pipeline.lib.reporting import summary as sheet
from pipeline.lib.robot.errormaps import as_geometry
from pipeline.lib.robot.kinematics import nominal_geometry
from pipeline.lib.robot.robots import nominal_robot
from pipeline.stages import report

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
    cover = np.zeros((6, 360))
    cover[:, 90:270] = 1.0                                  # every joint measured over half a turn
    maps = {"amap_coef": 1e-4 * np.sin(np.arange(360) / 20.0)[None] * np.arange(1, 7)[:, None], "amap_cover": cover}
    model = make_model(params["model"], {**nominal_geometry(nominal_robot("ur5")), **as_geometry(maps)})
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
                       "validation", "error_maps"}
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
    assert "`python -m pipeline.commands.ablation` (`--engine ray` in parallel)" in text
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
    from pipeline.commands import ablation
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


def test_the_ablation_summary_says_how_many_seeds_each_mean_holds_and_which_groups_failed(tmp_path, monkeypatch):
    """A review (2026-12-06): a group's failed seeds were dropped from its mean unsaid (3 of 5 beside another's 5),
    and a group whose every seed failed vanished from ablation.json and .md: a loser unreported. One seed's
    spread was ± 0.0000."""
    from pipeline.commands import ablation
    monkeypatch.chdir(tmp_path)
    run = lambda s, mae: {"seed": s, "test": {"3d": {"mae": mae, "rmse": 0.3, "r2": 0.9}}, "epochs_to_best": 10,
                          "n_params": 5}
    records = {"baseline": ([run(1, 0.25), run(2, 0.27)], []),
               "no_mask": ([run(1, 0.24)], [{"seed": 2, "error": "RuntimeError: NaN loss"}]),
               "paper_weights": ([], [{"seed": 1, "error": "MemoryError"}, {"seed": 2, "error": "MemoryError"}])}
    for g, (runs, failed) in records.items():
        write_json(tmp_path / "reports/ablation" / f"{g}.json",
                   {"group": g, "changes": ablation.GROUPS[g], "runs": runs, "failed": failed})
    summary = ablation.summarise()
    assert summary["groups"]["baseline"]["n"] == 2 and summary["groups"]["baseline"]["test_3d_mae_std"] == pytest.approx(0.01)
    assert summary["groups"]["no_mask"]["n"] == 1 and summary["groups"]["no_mask"]["test_3d_mae_std"] is None
    assert list(summary["all_seeds_failed"]) == ["paper_weights"]
    md = (tmp_path / "reports/ablation.md").read_text().splitlines()
    rows = {r.split("|")[1].strip(): [c.strip() for c in r.split("|")[1:-1]] for r in md[2:]}
    seeds = md[0].split("|")[1:-1].index(" seeds ")
    assert rows["baseline"][seeds] == "2" and rows["no_mask"][seeds] == "1 (1 failed)"
    assert rows["no_mask"][seeds + 1] == "0.2400 ± –"
    assert rows["paper_weights"][seeds] == "0 (2 failed)" and rows["paper_weights"][seeds + 1] == "every seed failed"
    assert_png(tmp_path / "reports/ablation.png")                       # one seed's group drawn without a bar
    for g in ("baseline", "no_mask"):                                   # no group left: still its figure, which
        (tmp_path / "reports/ablation" / f"{g}.json").unlink()          # ablation/dvc.yaml declares
    (tmp_path / "reports/ablation.png").unlink()
    assert ablation.summarise()["groups"] == {} and (tmp_path / "reports/ablation.png").exists()


def test_the_ablation_summary_leaves_out_groups_run_on_other_settings(tmp_path, monkeypatch):
    """`ablation sweep GROUP` re-runs some groups: the summary put them beside groups trained on other settings
    or inputs, in one table. Now it holds the groups run on those of the group run last, and lists the others."""
    import copy
    import os
    from pipeline.commands import ablation
    monkeypatch.chdir(tmp_path)
    for f in ablation.INPUTS:
        Path(f).parent.mkdir(parents=True, exist_ok=True)
        Path(f).write_bytes(b"inputs")
    params = load_params(ROOT / "params.yaml")
    first = ablation.settings_sha256(params)
    wider = copy.deepcopy(params)
    wider["model"]["d_model"] += 6
    assert ablation.settings_sha256(wider) != first
    Path(ablation.INPUTS[0]).write_bytes(b"other points")
    second = ablation.settings_sha256(params)
    assert second != first
    runs = [{"seed": 1, "test": {"3d": {"mae": 0.25, "rmse": 0.3, "r2": 0.9}}, "epochs_to_best": 10, "n_params": 5}]
    for k, (g, sha) in enumerate((("baseline", first), ("no_mask", first), ("paper_weights", second))):
        path = tmp_path / "reports/ablation" / f"{g}.json"
        write_json(path, {"group": g, "changes": ablation.GROUPS[g], "settings_sha256": sha, "runs": runs})
        os.utime(path, ns=(10**18 + k, 10**18 + k))                    # written in this order
    summary = ablation.summarise()
    assert set(summary["groups"]) == {"paper_weights"} and summary["stale"] == ["baseline", "no_mask"]
    assert "Left out, run on other settings or inputs than `paper_weights`" in (tmp_path / "reports/ablation.md").read_text()


def test_scatter_r2_is_the_metrics_r2():
    rng = np.random.default_rng(1)
    theory = rng.normal(0, 100, (50, 3))
    real = theory + rng.normal(0, 1, (50, 3))
    pred = theory + 0.7 * (real - theory) + rng.normal(0, 0.1, (50, 3))
    m = regression_metrics(pred, real, theory)
    for k, a in enumerate(AXES):
        assert figures.r2((real - theory)[:, k], (pred - theory)[:, k]) == pytest.approx(m[a]["r2"])


def test_figures_are_one_registry_with_captions():
    assert "ablation" not in figures.FIGURES                 # drawn by pipeline.commands.ablation, not the report
    for name, fn in figures.FIGURES.items():
        assert re.fullmatch(r"[a-z0-9_]+", name)
        assert len(figures.caption(fn)) > 20, name
    assert len(figures.caption(figures.fig_ablation)) > 20


# ---------------------------------------------------------------- the customer's summary (issue 33)

SUMMARY_INPUTS = ["params.yaml", "data/interim/predictions.parquet", "data/interim/baselines.parquet",
                  "data/interim/ingest.parquet"] + [f"reports/{n}.json" for n in (
                      "metrics", "ingest", "frame", "theory", "split", "calibration", "parts", "validation")]
WRITE_SUMMARY = ("from pipeline.stages import report; from pipeline.lib.project.config import for_stage, load_params; "
                 "report.Context(for_stage(load_params(), report.PARAMS)).write_summary()")


def md_table(text: str, heading: str) -> tuple[list, dict]:
    """The header and {first cell: row} of the first table under the `## heading...` line."""
    lines = text[text.index("## " + heading):].splitlines()
    rows = [[c.strip() for c in ln.strip().strip("|").split("|")] for ln in lines if ln.startswith("|")]
    head, body = rows[0], rows[2:]
    end = next((k for k, ln in enumerate(lines[1:], 1) if ln.startswith("## ")), len(lines))
    body = body[:sum(1 for ln in lines[:end] if ln.startswith("|")) - 2]
    return head, {r[0]: r for r in body}


def pdf_text(data: bytes) -> str:
    """The PDF's text: pypdf's when it is installed; else every literal string of each text object
    (BT ... ET) of its Flate content streams, joined (matplotlib writes ASCII text as strings)."""
    try:
        import io
        import pypdf
        reader = pypdf.PdfReader(io.BytesIO(data))
        assert len(reader.pages) == 1
        return reader.pages[0].extract_text()
    except ImportError:
        pass
    out = []
    for m in re.finditer(rb"stream\r?\n(.*?)\r?\nendstream", data, re.S):
        try:
            s = zlib.decompress(m.group(1))
        except zlib.error:
            continue
        for bt in re.findall(rb"BT(.*?)ET", s, re.S):
            parts = re.findall(rb"\(((?:\\.|[^\\)])*)\)", bt)
            out.append(b"".join(re.sub(rb"\\(.)", rb"\1", p) for p in parts).decode("latin-1"))
    return "\n".join(out)


def test_summary_page_numbers_are_the_artifacts_and_one_reproducible_a4_page(trained_project, tmp_path,
                                                                               monkeypatch):
    for f in SUMMARY_INPUTS:                               # the project's artifacts, read only: a copy
        if (trained_project / f).exists():
            (tmp_path / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(trained_project / f, tmp_path / f)
    monkeypatch.chdir(tmp_path)
    params = for_stage(load_params(), report.PARAMS)
    assert report.Context(params).write_summary()["pages"] == 1
    md = (tmp_path / "reports/summary.md").read_text()
    m, v, sp = (read_json(f"reports/{n}.json") for n in ("metrics", "validation", "split"))
    cal, parts = read_json("reports/calibration.json"), read_json("reports/parts.json")
    campaigns = v["campaigns"]

    _, rows = md_table(md, "Campaigns")                    # points per campaign
    for c, n in sp["per_campaign"].items():
        assert f"test {n['test']}" in rows[f"`{c}`"][1] and rows[f"`{c}`"][2].startswith(f"{sum(n.values())} / ")
    for c, val in campaigns.items():
        assert rows[f"`{c}`"][2] == f"{val['ingest']['n_kept']} / {len(val['ingest']['dropped'])}"

    head, rows = md_table(md, "Accuracy")                  # mean / p95 / max per method
    col = {name: head.index(label) for name, label in sheet.METHODS.items()}
    cells = lambda row, name: [float(x) for x in row[col[name]].split(" / ")]
    r3 = lambda x: round(x, 3)
    pred = pd.read_parquet("data/interim/predictions.parquet").merge(
        pd.read_parquet("data/interim/baselines.parquet"), on="point_id", how="left")
    for c in sp["per_campaign"]:
        row, mc, cc = rows[f"`{c}`, test split"], m["campaigns"][c], cal["campaigns"][c]["test"]
        test = pred[(pred.split == "test") & (pred.campaign == c)]
        assert int(row[1]) == sp["per_campaign"][c]["test"] == cc["n"]
        errors = {"nominal": test[THEORY].to_numpy(), "calibrated": test[[f"calibrated_dh_{a}" for a in AXES]].to_numpy(),
                  "calibrated_parts": test[[f"calibrated_parts_{a}" for a in AXES]].to_numpy(),
                  "model": test[PRED].to_numpy()}
        for name, key in (("nominal", "nominal_dh"), ("calibrated", "calibrated_dh"),
                          ("calibrated_parts", "calibrated_parts"), ("model", m["model"])):
            mean, p95, mx = cells(row, name)
            e = np.linalg.norm(errors[name] - test[MEAS].to_numpy(), axis=1)
            assert mean == r3(mc[key]["test"]["mae"]) and p95 == r3(np.percentile(e, 95)) and mx == r3(e.max())
        assert cells(row, "nominal")[2] == r3(cc["nominal"]["max_mm"])
        assert cells(row, "calibrated")[2] == r3(cc["calibrated"]["max_mm"])
        if len(sp["per_campaign"]) == 1:
            assert cells(row, "calibrated_parts")[2] == r3(parts["splits"]["test"]["calibrated_parts"]["max_mm"])
    for c, val in campaigns.items():
        row = rows[f"`{c}`"]
        assert int(row[1]) == val["n_judged"]
        for name in sheet.METHODS:
            assert cells(row, name) == [r3(val[k][name]) for k in ("mean_3d_mm", "p95_3d_mm", "max_3d_mm")]
        assert f"{round(100 * (1 - val['in_workspace_share']))}% of `{c}`" in md     # outside the workspace
        if val["frame"] != "same":
            assert f"`{c}` ({val['n_register']} points" in md                        # registered on its own points
    assert f"{round(100 * (1 - m['uncertainty']['test']['in_workspace_share']))}% of the test split" in md
    assert "**Instrument:** not recorded (set `summary.instrument`)" in md
    if not any(val.get("position_accuracy") for val in campaigns.values()):
        assert "**ISO 9283 AP_P / RP:**" in md

    pdf = (tmp_path / "reports/summary.pdf").read_bytes()
    assert pdf.startswith(b"%PDF-") and len(re.findall(rb"/Type\s*/Page\b", pdf)) == 1
    assert re.search(rb"/MediaBox\s*\[\s*0 0 595\.44 841\.68\s*\]", pdf)            # A4, in points
    assert b"CreationDate" not in pdf and b"ModDate" not in pdf
    text = pdf_text(pdf)
    for row in rows.values():                               # every accuracy number is on the page
        for name in sheet.METHODS:
            assert row[col[name]] in text, row[col[name]]

    md_bytes = (tmp_path / "reports/summary.md").read_bytes()  # another process, the same bytes
    subprocess.run([sys.executable, "-c", WRITE_SUMMARY], cwd=tmp_path, check=True, capture_output=True,
                   env={**__import__("os").environ, "PYTHONPATH": str(ROOT)})
    assert (tmp_path / "reports/summary.pdf").read_bytes() == pdf
    assert (tmp_path / "reports/summary.md").read_bytes() == md_bytes


def test_summary_shows_dates_temperatures_and_iso_9283_where_recorded():
    assert sheet.date_range(np.array([2.02011e13, 2.02011e13])) == "2020-11"        # a spreadsheet kept the month
    assert sheet.date_range(np.array([20201103.0, 20201105.0])) == "2020-11-03 – 2020-11-05"
    assert sheet.date_range(["2021-03-02T10:00", "2021-03-04 09:00"]) == "2021-03-02 – 2021-03-04"
    assert sheet.date_range(np.array([1.5, 2.5])) is None and sheet.time_column(["j1_deg", "Timestamp"]) == "Timestamp"
    table = pd.DataFrame({"campaign": ["c"] * 3, "Timestamp": [2.02011e13] * 3, "temp": [21.68, 22.0, 22.24]})
    cond = sheet.conditions(table, "temp")
    assert cond["c"]["dates"] == "2020-11" and sheet.temperature_text(cond["c"]) == "21.7–22.2 °C"
    assert sheet.conditions(table, None)["c"]["t_mean"] is None

    params = load_params(ROOT / "params.yaml")
    params["validate"]["campaigns"] = {"cubes": {"commanded": {"columns": ["x", "y", "z"]}, "frame": "refit_tool"}}
    stats = {"n": 5, "mean": 0.5, "p95": 0.9, "max": 1.0}
    val = {"n": 40, "n_judged": 30, "frame": "refit_tool", "n_register": 10, "in_workspace_share": 0.25,
           **{k: {mm: 0.5 for mm in sheet.METHODS} for k in ("mean_3d_mm", "p95_3d_mm", "max_3d_mm")},
           "angle_map": {"in_range_share": 0.9}, "ingest": {"n_kept": 40, "dropped": []},
           "thermal": {"temperature_c": 20.75, "dT_k": -1.25},
           "position_accuracy": {mm: {"positions": 12, "positions_repeated": 0, "ap_measured_mm": 0.8123,
                                      "rp_measured_mm": None, "rp_iso_measured_mm": None, "bar_error_mm": 0.1 * k,
                                      "ap_after_registration": True}
                                 for k, mm in enumerate(sheet.METHODS)}}
    metrics = {"model": "spi_boter_calibrated", "uncertainty": {"test": {"in_workspace_share": 0.9}}}
    s = {"validation": {"campaigns": {"cubes": val}}, "split": {"per_campaign": {"c": {"train": 8, "test": 2}}},
         "frame": {"tool_mm": [0.0, 0.0, 109.0]}, "ingest": {"campaigns": {"c": {"n_kept": 11, "n_dropped": 1}}}}
    test = {"c": {"n": 2, **{mm: stats for mm in sheet.METHODS}}}
    md = sheet.markdown(sheet.blocks(params, metrics, s, test, cond, ["measurement_rx", "measurement_ry"]))
    head, rows = md_table(md, "ISO 9283")
    assert rows["`cubes`"][1:4] == ["12 (0 repeated)", "0.812 *", "–"]            # Series_D's cubes: no RP; AP_P
    assert "* AP_P after a registration to the model's own prediction" in md      # after its refit_tool registration
    assert rows["`cubes`"][4:] == ["0.000", "0.100", "0.200", "0.300"]
    _, rows = md_table(md, "Campaigns")
    assert rows["`c`"][2:] == ["10 / 2 (1 at ingest, 1 frame outliers)", "2020-11", "21.7–22.2 °C"]
    assert rows["`cubes`"][4] == "20.8 °C (mean; -1.2 K)"
    assert "judged outside that range: `cubes` at 20.8 °C" in md and "`measurement_rx`" in md
    assert "(0.000, 0.000, 109.000) mm" in md and "75% of `cubes`" in md and "probe offset too" in md


def test_the_summary_names_the_instrument_when_it_is_set(tmp_path, monkeypatch):
    params = small_params()
    monkeypatch.chdir(tmp_path)
    write_inputs(tmp_path, params)
    report.run(params)
    assert "**Instrument:** not recorded (set `summary.instrument`)." in (tmp_path / "reports/summary.md").read_text()
    params["summary"]["instrument"] = "Leica AT960 laser tracker, T-Mac probe"
    report.run(params)
    assert "**Instrument:** Leica AT960 laser tracker, T-Mac probe." in (tmp_path / "reports/summary.md").read_text()


def test_the_summary_says_how_a_custom_robots_table_was_given_and_what_was_calibrated():
    """Review (2026-11-29): a custom robot's table given in modified DH read "standard Denavit-Hartenberg ... from
    its own DH table", and a calibration without joint compliance (no link masses) read "elasto-geometric"."""
    custom = {"model": "custom", "tool_mm": [0.0, 0.0, 0.0], "dh": {"convention": "modified"}}
    assert "given in modified DH (Craig) and converted" in sheet.robot_text(custom, None, False)[0]
    assert "modified" not in sheet.robot_text({**custom, "dh": {}}, None, False)[0]
    rigid = {"identified": ["d1", "a2", "offset3", "beta2"], "n_candidates": 30}
    assert "classical geometric calibration (4 of 30" in sheet.method_text({}, rigid, None)
    elastic = {**rigid, "identified": rigid["identified"] + ["c2"]}
    assert "classical elasto-geometric calibration (5 of 30" in sheet.method_text({}, elastic, None)
    off = {"model": "spi_boter_calibrated", "reported": {"method": "calibrated_parts", "network": False}}
    assert "network on top" not in sheet.method_text(off, elastic, None)     # a review: it said so, network off
    assert "is not served: the robot cell gets `calibrated_parts`" in sheet.method_text(off, elastic, None)

"""The parts stage on the twin, whose joints carry a fine angular structure (issue 22), and the held-out
region split that judges extrapolation."""
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.lib.learning.splits import region
from pipeline.lib.project.config import load_params, read_json
from pipeline.lib.sim import twin as T
from pipeline.stages import calibrate, frame, ingest, parts, split, theory

ROOT = Path(__file__).resolve().parents[1]
PARAMS = load_params(ROOT / "params.yaml")


@pytest.fixture(scope="module")
def twin_project(tmp_path_factory):
    """ingest .. parts on the bundled twin campaign, in a scratch directory."""
    d = tmp_path_factory.mktemp("twin")
    p = json.loads(json.dumps(PARAMS))
    for k in ("joints", "tracker"):
        p["ingest"][k] = str(ROOT / p["ingest"][k])
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(d)
        for stage in (ingest, frame, theory, split, calibrate, parts):
            stage.run(p)
        yield d, read_json("reports/parts.json"), read_json("models/parts.json")


def test_the_twins_fine_structure_is_in_its_joints():
    """Tens of arcseconds with features of 5-20° on every joint: what the IPA UR10 shows."""
    twin, plain = T.Twin(), T.Twin(errors={**T.sample_errors(), "fine_amp_arcsec": np.zeros((6, 3))})
    q = np.tile(np.array([[0.0, -90.0, 90.0, -90.0, 90.0, 0.0]]), (721, 1))
    q[:, 1] = np.linspace(-150, -30, 721)                              # joint 2 swept in 1/6 degree steps
    d = (twin.actual_joints(q) - plain.actual_joints(q))[:, 1] * 3600   # arcsec
    assert 10 < d.std() < 60 and np.abs(d).max() < 150
    f = np.abs(np.fft.rfft(d - d.mean()))
    period = 120.0 / np.argmax(f)                                       # degrees: the strongest component
    assert 5 <= period <= 20


def test_the_maps_take_the_twins_joint_structure(twin_project):
    _, report, saved = twin_project
    s = report["splits"]
    assert report["enabled"] and saved["enabled"]
    assert s["val"]["calibrated_parts"]["mean_mm"] < 0.6 * s["val"]["calibrated"]["mean_mm"]
    assert s["test"]["calibrated_parts"]["mean_mm"] < 0.6 * s["test"]["calibrated"]["mean_mm"]
    angle = {b["joint"]: b for b in report["blocks"] if b["part"] == "angle_map"}
    assert {j for j, b in angle.items() if b["coef_rms_arcsec"] > 5} >= {1, 2, 3}      # the twin's FINE amplitudes
    assert max(b["relearned_share"] for b in angle.values()) < 0.5    # no angle map is a calibration parameter
    assert set(report["calibration_corrections"]) >= {"a2", "a3", "offset2", "c2"}
    assert "amap_coef" in saved["geometry"] and np.asarray(saved["geometry"]["amap_cover"]).shape == (6, 360)


def test_a_held_out_region_is_never_trained_on():
    q = T.sample_poses(400, np.random.default_rng(5))
    held = region(q, {"joints": [2, 3], "quantile": 0.5})
    assert 0.05 < held.mean() < 0.35                                  # two joints above their medians (correlated)
    assert (q[held, 1] > np.median(q[:, 1])).all() and (q[held, 2] > np.median(q[:, 2])).all()
    assert not region(q, None).any()


def test_the_split_stage_holds_out_the_region(tmp_path, monkeypatch, twin_project):
    d, _, _ = twin_project
    monkeypatch.chdir(tmp_path)
    Path("data/interim").mkdir(parents=True)
    Path("data/interim/points.parquet").write_bytes((d / "data/interim/points.parquet").read_bytes())
    p = json.loads(json.dumps(PARAMS))
    p["split"]["holdout"] = {"joints": [2, 3], "quantile": 0.5}
    out = split.run(p)
    table = pd.read_parquet("data/interim/split.parquet")
    assert out["counts"]["holdout"] == (table.split == "holdout").sum() > 40
    assert out["counts"]["train"] + out["counts"]["val"] + out["counts"]["test"] + out["counts"]["holdout"] == len(table)


def test_a_thermal_column_the_ingest_table_lacks_is_named_before_the_fit(twin_project):
    """A review (2026-12-06): parts.thermal.column naming no column of the ingest table stopped the stage after
    the whole map fit with pyarrow's words and the table's schema, naming no setting."""
    d, _, _ = twin_project
    p = json.loads(json.dumps(PARAMS))
    p["parts"]["thermal"]["column"] = "temp_c"
    before = (d / "reports/parts.json").read_bytes()
    with pytest.raises(ValueError, match=r"params.yaml parts.thermal.column: 'temp_c' is not a column of "
                                         r"data/interim/ingest.parquet \(it has .*j1_deg"):
        parts.run(p, d)
    assert (d / "reports/parts.json").read_bytes() == before

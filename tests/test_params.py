"""params.yaml owns every setting: the stages accept exactly its keys, and say which when not."""
import copy
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.lib.project.config import SECTIONS, ParamsError, load_params, section
from pipeline.stages import split

ROOT = Path(__file__).resolve().parents[1]
PARAMS = load_params(ROOT / "params.yaml")


def test_committed_params_have_exactly_the_known_keys():
    assert set(PARAMS) == {k for k in SECTIONS if "." not in k}
    for name in PARAMS:
        section(PARAMS, name)                              # raises on any difference


def test_misspelt_key_stops_the_stage_listing_the_valid_keys(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    p = copy.deepcopy(PARAMS)
    p["split"]["sed"] = p["split"].pop("seed")
    with pytest.raises(ParamsError) as e:
        split.run(p)
    msg = str(e.value)
    assert "params.yaml split: unknown key(s) ['sed']; missing key(s) ['seed']" in msg
    assert "Valid keys: seed, fractions" in msg
    assert not (tmp_path / "data").exists()                # stopped before reading or writing


def test_nested_sections_and_missing_sections_are_checked():
    p = copy.deepcopy(PARAMS)
    p["ingest"]["columns"]["positions"] = p["ingest"]["columns"].pop("position")
    with pytest.raises(ParamsError, match=r"ingest.columns: unknown key\(s\) \['positions'\].*"
                                          r"Valid keys: point_id, joints, position"):
        section(p, "ingest")
    del p["train"]
    with pytest.raises(ParamsError, match="missing section 'train'"):
        section(p, "train")


# Issue 32, major 10: settings accepted as garbage, or ending in a NumPy/torch traceback without the key
@pytest.mark.parametrize("key, value, message", [
    ("split.fractions", [0.7, 0.1, 0.1, 0.1], "three fractions > 0"),
    ("split.fractions", [0, 0, 1], "three fractions > 0"),
    ("split.fractions", [0.8, 0.1, 0.2], "sum to 1"),
    ("split.seed", "7", "an integer >= 0"),
    ("split.holdout", {"joints": [0], "quantile": 0.5}, "joint numbers 1-6"),
    ("split.holdout", {"joints": [2, 3], "quantile": 1.5}, r"a quantile in \(0, 1\]"),
    ("train.batch_size", 0, "an integer >= 1"),
    ("train.max_epochs", 0, "an integer >= 1"),
    ("serve.max_batch", 0, "an integer >= 1"),
    ("serve.timeout_s", -1, "a time > 0 s"),
    ("serve.max_items", True, "an integer >= 1"),
    ("compensate.tol_mm", float("nan"), "a tolerance > 0 mm"),
    ("model.d_model", 0, "an integer >= 1"),                                 # issue 35: checked here, once
    ("model.n_head", 2.0, "an integer >= 1"),
    ("model.fade_to", 1.0, "null or a number of workspace radii > 1"),
    ("model.physics", "learned", "nominal or calibrated"),
    ("compensate.jacobian_of", "numeric", "physics or model"),
    ("calibrate.tilt_joints", [2, 7], "distinct joint numbers 1-6"),
    ("plan.handshake_io", 9, "null or a standard digital I/O number 0-7"),
])
def test_a_bad_value_stops_naming_its_key(key, value, message):
    p = copy.deepcopy(PARAMS)
    name, k = key.split(".")
    p[name][k] = value
    shown = key if "holdout" not in key else "split.holdout." + ("joints" if "joint" in message else "quantile")
    with pytest.raises(ParamsError, match=rf"params.yaml {re.escape(shown)}: .*{message}"):
        section(p, name)


def test_a_key_given_twice_or_an_empty_file_is_refused(tmp_path):
    twice = tmp_path / "twice.yaml"
    twice.write_text("split:\n  seed: 7\n  fractions: [0.8, 0.1, 0.1]\n  seed: 8\n")
    with pytest.raises(ParamsError, match=r"line 4: the key 'seed' is given twice"):
        load_params(twice)
    empty = tmp_path / "empty.yaml"
    empty.write_text("# nothing\n")
    with pytest.raises(ParamsError, match="expected a mapping of sections .* got an empty file"):
        load_params(empty)


def test_split_writes_both_files_or_neither(tmp_path, monkeypatch):
    """Minor: with reports/ unwritable, split wrote its parquet and then failed on its JSON."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "data/interim").mkdir(parents=True)
    pd.DataFrame({"point_id": [f"P{i}" for i in range(20)], "campaign": "main",
                  **{f"j{j}_deg": np.arange(20.0) for j in range(1, 7)}}).to_parquet("data/interim/points.parquet")
    (tmp_path / "reports").write_text("a file where the folder should be")
    with pytest.raises(OSError):
        split.run(copy.deepcopy(PARAMS))
    assert not (tmp_path / "data/interim/split.parquet").exists()
    (tmp_path / "reports").unlink()
    assert sum(split.run(copy.deepcopy(PARAMS))["counts"].values()) == 20
    assert (tmp_path / "data/interim/split.parquet").exists() and (tmp_path / "reports/split.json").exists()

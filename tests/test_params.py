"""params.yaml owns every setting: the stages accept exactly its keys, and say which when not."""
import copy
from pathlib import Path

import pytest

from pipeline import split
from pipeline.lib.config import SECTIONS, ParamsError, load_params, section

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

"""Presets: deep merge, in-process use, and rewriting params.yaml with its comments."""
from pathlib import Path

import pytest
import yaml

from pipeline.commands.preset import main
from pipeline.lib.project.config import section
from pipeline.lib.reading.presets import PRESETS, apply_preset, changes, deep_merge, merged_params

ROOT = Path(__file__).resolve().parents[1]
BASE = yaml.safe_load((ROOT / "params.yaml").read_text())


def leaves(d, prefix=""):
    for k, v in d.items():
        if isinstance(v, dict) and v and k not in ("campaigns", "tcp"):   # maps of the user's own names
            yield from leaves(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}"


def test_deep_merge_merges_mappings_and_replaces_the_rest():
    base = {"a": {"b": 1, "c": [1, 2]}, "d": 3}
    out = deep_merge(base, {"a": {"c": [9]}, "e": {"f": None}})
    assert out == {"a": {"b": 1, "c": [9]}, "d": 3, "e": {"f": None}}
    assert base == {"a": {"b": 1, "c": [1, 2]}, "d": 3}           # untouched
    assert changes(base, out) == [("a.c", [1, 2], [9]), ("e", None, {"f": None})]



def test_a_target_geometry_is_replaced_whole():
    """ingest.target (a rigid target's markers) over another: the markers of the one on top only."""
    base = {"ingest": {"target": {"markers": {"A": [0, 0, 0], "B": [1, 0, 0], "C": [0, 1, 0]}}, "sep": ","}}
    out = deep_merge(base, {"ingest": {"target": {"markers": {"P": [0, 0, 0], "Q": [2, 0, 0], "R": [0, 2, 0]}}}})
    assert out == {"ingest": {"target": {"markers": {"P": [0, 0, 0], "Q": [2, 0, 0], "R": [0, 2, 0]}}, "sep": ","}}

@pytest.mark.parametrize("name", ["gtpn-ur5", "ipa-ur10"])
def test_presets_only_set_known_keys(name):
    preset = yaml.safe_load((PRESETS / f"{name}.yaml").read_text())
    assert preset.pop("extends") == "twin"                        # over the twin's settings (the next test)
    known = set(leaves(BASE))
    assert set(leaves(preset)) <= known, set(leaves(preset)) - known
    merged = merged_params(name, BASE)
    assert merged["split"] == BASE["split"]                       # the rest kept
    assert merged["ingest"]["joints"].startswith("../shared/datasets/")
    assert merged["ingest"]["tracker"] == merged["ingest"]["joints"]      # one table
    assert merged["ingest"]["gross_outlier_mm"] == BASE["ingest"]["gross_outlier_mm"]
    for sec in merged:                                            # a valid params file
        section(merged, sec)


def test_ipa_preset_settings():
    p = merged_params("ipa-ur10", BASE)
    assert set(p["validate"]["campaigns"]) == {"series_b_same", "series_b_refit", "series_d"}   # replaced, not merged
    assert p["validate"]["campaigns"]["series_d"]["frame"] == "refit_tool"
    assert p["parts"]["thermal"] == {"column": "measurement_temperature", "cte_per_k": BASE["parts"]["thermal"]["cte_per_k"]}
    for sec in p:
        section(p, sec)
    assert p["robot"]["model"] == "ur10" and p["robot"]["tool_mm"] == [0.0, 0.0, 109.0]
    assert p["frame"]["estimate_tool"] is True
    assert (p["ingest"]["sep"], p["ingest"]["decimal"], p["ingest"]["angle_unit"]) == (";", ",", "rad")


def test_apply_rewrites_params_keeping_comments(tmp_path, capsys):
    path = tmp_path / "params.yaml"
    text = (ROOT / "params.yaml").read_text()
    path.write_text(text)
    main(["gtpn-ur5", "--params", str(path)])
    out = capsys.readouterr().out
    assert "ingest.joints: 'data/raw/joints.csv' -> '../shared/datasets/gtpn-ur5/merge2copy.csv'" in out
    assert "ingest.columns.joints: None -> ['1', '2', '3', '4', '5', '6']" in out
    new = path.read_text()
    assert yaml.safe_load(new) == merged_params("gtpn-ur5", yaml.safe_load(text))
    for line in text.splitlines():                                # comments survive
        if line.lstrip().startswith("#"):
            assert line in new
    assert "# ur3 | ur5 | ur10 | ur3e | ur5e | ur10e | ur16e | ur20 | ur30 | custom" in new and "dh: null" in new
    assert apply_preset("gtpn-ur5", path) == []                   # idempotent
    assert apply_preset("ipa-ur10", path) != []
    assert yaml.safe_load(path.read_text())["robot"]["model"] == "ur10"


def test_unknown_preset():
    with pytest.raises(ValueError, match="unknown preset 'nope'; known: gtpn-ur5, ipa-ur10"):
        merged_params("nope", BASE)


def test_apply_after_dvc_rewrote_params_in_block_style(tmp_path):
    """`dvc exp run -S` rewrites params.yaml with block lists; a preset applied after it keeps valid YAML."""
    from ruamel.yaml import YAML
    path = tmp_path / "params.yaml"
    rt = YAML()
    doc = rt.load((ROOT / "params.yaml").read_text())
    for sec in doc.values():                                     # every list in block style, as DVC does
        for k, v in list(sec.items()):
            if isinstance(v, list):
                v.fa.set_block_style()
    with open(path, "w") as f:
        rt.dump(doc, f)
    before = yaml.safe_load(path.read_text())
    assert apply_preset("ipa-ur10", path) != []
    assert yaml.safe_load(path.read_text()) == merged_params("ipa-ur10", before)


@pytest.mark.parametrize("name", sorted(p.stem for p in PRESETS.glob("*.yaml")))
def test_every_preset_merged_onto_params_passes_every_rule(name):
    merged = merged_params(name, BASE)
    for sec in merged:                                            # keys and values (config.RULES)
        section(merged, sec)


def test_a_bad_preset_name_is_one_line(capsys):
    """Review D: an unknown preset or a folder for a name was a traceback; now one line, exit 2."""
    from pipeline.commands import preset as cmd
    with pytest.raises(SystemExit) as e:
        cmd.main(["nosuch", "--params", "params.yaml"])
    assert e.value.code == 2 and "preset: error: unknown preset 'nosuch'" in capsys.readouterr().err


def test_the_printed_changes_name_a_replaced_mapping_s_keys_that_are_gone(tmp_path, capsys):
    """gtpn-ur5 replaces validate.campaigns whole: the twin's twin_side campaign left params.yaml unprinted,
    though the command says it prints what changed."""
    path = tmp_path / "params.yaml"
    path.write_text((ROOT / "params.yaml").read_text())
    assert "twin_side" in yaml.safe_load(path.read_text())["validate"]["campaigns"]
    main(["gtpn-ur5", "--params", str(path)])
    out = capsys.readouterr().out
    assert "twin_side" not in yaml.safe_load(path.read_text())["validate"]["campaigns"]
    assert any(line.startswith("validate.campaigns.twin_side: {") and line.endswith("} removed")
               for line in out.splitlines())


def test_a_preset_gives_the_same_params_whichever_was_applied_before():
    """A review (2026-12-06, evening): a preset merged over what params.yaml held, so one applied after another kept
    the other's settings where it said nothing: ipa-ur10 after ipa-ur10-cb trained on Series_B too and validated
    on it (series_b_same), gtpn-ur5 after twin-2stations kept station_b, after ipa-ur10 its three TCPs. Every preset
    now states every key any preset sets (the others `extends: twin`, whose values are the committed params'), and
    robot.tcp is replaced whole: any preset over any other is that preset over the committed params."""
    base = yaml.safe_load((ROOT / "params.yaml").read_text())
    names = sorted(p.stem for p in PRESETS.glob("*.yaml"))
    assert {"twin", "gtpn-ur5", "ipa-ur10", "ipa-ur10-cb", "twin-2stations"} <= set(names)
    assert changes(base, merged_params("twin", base)) == []                       # the committed params are the twin's
    for a in names:
        for b in names:
            after = merged_params(b, merged_params(a, base))
            assert changes(merged_params(b, base), after) == [], (a, b, changes(merged_params(b, base), after)[:5])
    assert merged_params("ipa-ur10", merged_params("ipa-ur10-cb", base))["campaigns"]["more"] == {}

"""params.yaml owns every setting: the stages accept exactly its keys, and say which when not."""
import copy
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial import cKDTree

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


def test_params_are_read_as_dvc_reads_them(tmp_path):
    """A review (2026-12-06): params.yaml was read as YAML 1.1 (PyYAML) where DVC reads YAML 1.2 (ruamel): a
    hand-written `lr: 1e-4` was refused as the string '1e-4', a point-id column named `No` was the boolean
    False, `on` True, while dvc.lock and `dvc exp show` recorded 0.0001, 'No' and 'on'. Now the values are
    DVC's own reading's; a file that is not YAML names its line."""
    from dvc.utils.serialize import parse_yaml
    text = (ROOT / "params.yaml").read_text()
    text = text.replace("  lr: 1.0e-4 ", "  lr: 1e-4   ", 1).replace("    point_id: null", "    point_id: No", 1)
    text = text.replace("  instrument: null", "  instrument: on", 1)
    f = tmp_path / "params.yaml"
    f.write_text(text)
    got = load_params(f)
    assert got == parse_yaml(text, str(f))                             # DVC's reading, to the value
    assert (got["train"]["lr"], got["ingest"]["columns"]["point_id"], got["summary"]["instrument"]) == (1e-4, "No", "on")
    assert section(got, "train")["lr"] == 1e-4 and section(got, "ingest")["columns"]["point_id"] == "No"
    f.write_text("split:\n  seed: 7\n  fractions: [0.8, 0.1\n")
    with pytest.raises(ParamsError, match=r"params.yaml line \d: not YAML"):
        load_params(f)


def test_what_the_project_writes_as_yaml_it_reads_back_the_same_and_presets_read_as_params(tmp_path):
    """A review (2026-12-06): with params read as YAML 1.2, the fleet, bench and preset writers still wrote with
    PyYAML, which leaves '1e3' or '0o17' bare (a string to YAML 1.1, a number to 1.2): a robot's point-id column
    '1e3' came back 1000.0; a preset's `lr: 2e-4` was written '2e-4' and `point_id: No` false."""
    from pipeline.lib.project.config import yaml_text, yaml_values
    from pipeline.lib.reading.presets import apply_preset
    tricky = {"ingest": {"columns": {"point_id": "1e3"}}, "summary": {"instrument": "0o17"},
              "x": ["No", "on", "1_000", "+1e3", "1.5e3", None, True, 1e-4, 10], "z_first": 1, "a_then": 2}
    text = yaml_text(tricky)
    assert yaml_values(text, "t") == tricky and list(yaml_values(text, "t")) == list(tricky)   # values, order
    f = tmp_path / "params.yaml"
    f.write_text((ROOT / "params.yaml").read_text())
    preset = tmp_path / "mine.yaml"
    preset.write_text("train: {lr: 2e-4}\ningest: {columns: {point_id: No}}\n")
    apply_preset(preset, f)
    got = load_params(f)
    assert got["train"]["lr"] == 2e-4 and got["ingest"]["columns"]["point_id"] == "No"
    assert section(got, "train")["lr"] == 2e-4


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


NAN = float("nan")


# Keys a review found unchecked (each value tried in a clone, running the stage): accepted as garbage, or a
# traceback deep in NumPy, scipy or torch without the key. Nested keys (plan.rules.radius_mm) are set in place.
@pytest.mark.parametrize("key, value", [
    ("plan.cover_k", "2"), ("plan.cover_k", 0), ("plan.cover_k", -1),
    ("plan.per_waypoint", 2.5), ("plan.per_waypoint", -3),
    ("plan.region", 10.5), ("plan.region", -5),
    ("plan.region_margin_deg", NAN), ("plan.region_margin_deg", "x"), ("plan.region_margin_deg", -30),
    ("plan.seed", 1.5), ("plan.seed", "a"), ("plan.seed", -1),
    ("plan.settle_s", 0), ("plan.acc", NAN), ("plan.vel", "1"),
    # a review: written with 6 decimals, 4e-7 became `settle = 0.000000`, `acc = 0.000000`, `stopj(0.000000)`
    ("plan.settle_s", 4e-7), ("plan.acc", 4e-7), ("program.movej.acc", 4e-7), ("program.movej.vel", 9e-4),
    ("program.movel.acc", 4e-7), ("program.movel.vel", 4e-7),
    # a slip of unit went into the script as written: deg/s as rad/s, mm/s as m/s, mm/s² as m/s²
    ("program.movej.vel", 60), ("program.movej.acc", 80.0), ("program.movel.vel", 250), ("program.movel.acc", 1200),
    ("plan.vel", 30.0), ("plan.acc", 100),
    # a review: written as given (settle = 1e30 s; a path at 100 m/s; the branch-flip guard off at 1e6 mm)
    ("plan.settle_s", 1e30), ("path.speed_mm_s", 1e5), ("path.max_deviation_mm", 1e6),
    ("plan.rules.radius_mm", [300]), ("plan.rules.radius_mm", "x"), ("plan.rules.radius_mm", [850.0, 300.0]),
    ("plan.rules.height_mm", [0.0, NAN]),
    ("plan.rules.elbow_min_mm", -1e9), ("plan.rules.table_mm", "40"), ("plan.rules.sin_wrist", -1),
    ("plan.rules.sin_elbow", 1.0), ("plan.rules.column_mm", -5), ("plan.rules.elbow_up", "no"),
    ("plan.rules.tracker_side_deg", 0),
    ("frame.outlier_k", -1), ("frame.max_rms_mm", "x"), ("frame.outlier_min_mm", "x"), ("frame.robust_loss", "x"),
    ("frame.robust_scale_mm", NAN), ("frame.estimate_tool", "no"), ("frame.tool_per_station", 1),
    ("calibrate.params", []), ("calibrate.params", ["d", "d"]), ("calibrate.params", ["dh"]),
    ("calibrate.tol", "x"), ("calibrate.rank_tol", -1), ("calibrate.tol", -1), ("calibrate.max_nfev", 0),
    ("calibrate.loss_scale_mm", NAN), ("calibrate.loss_scale_mm", -1), ("calibrate.loss", "l2"),
    ("parts.angle_map.knot_deg", 0), ("parts.angle_map.knot_deg", -1), ("parts.angle_map.smooth_arcsec", 0),
    ("parts.load_map.smooth_arcsec", 0), ("parts.angle_map.joints", [7]), ("parts.noise_mm", 0),
    ("parts.noise_mm", -1), ("parts.angle_map.fade_deg", NAN), ("parts.load_map.joints", [9]),
    ("parts.angle_map.prior_arcsec", -5), ("parts.load_map.prior_arcsec", -5), ("parts.angle_map.reach_deg", -3),
    ("parts.load_map.knots", 1), ("parts.load_map.knots", 2.5), ("parts.thermal.cte_per_k", "x"),
    ("parts.thermal.column", ""),
    ("model.mask", "spy"), ("model.head", "mlp"), ("model.encoder", "yes"), ("model.alpha0", NAN),
    ("model.dropout", 1.0), ("model.init_seed", -1),
    ("loss.weighting", "equal"), ("loss.physics", "false"), ("loss.lambda_data", 0), ("loss.lambda_physics", NAN),
    ("train.weight_decay", -1e-6), ("train.grad_clip", 0), ("train.ema", 1.0), ("train.lr_drop", 1.5),
    ("train.lr_patience", 2.0), ("train.device", "gpu"),
    ("baselines.dnn", "yes"), ("baselines.other_physics", None),
    ("workspace.radius_quantile", 0), ("workspace.coverage", 90),
    ("validate.register_points", 2), ("validate.tool_rank_tol", -1),
    ("compensate.solver", "newton"), ("compensate.lr", 0), ("compensate.tol_mse", NAN),
    ("compensate.drive_check", "no"), ("compensate.twin", None), ("compensate.drive_seed", 1.5),
    ("ablation.seeds", []), ("ablation.seeds", [139, 139]), ("ablation.max_epochs", 0),
    ("serve.host", ""), ("serve.onnx", "true"), ("serve.compile", 0), ("serve.call_budget_ms", 0),
    ("serve.lm_per_call", 0), ("serve.max_connections", 0),
    ("summary.instrument", 5),
    ("robot.tcp", {"marker": {"xyz_mm": [0, 0, 200]}}),          # the probe's frame in ur_calibration.yaml
    # a review (2026-12-06, evening): an integer of 400 digits gave OverflowError (math.isfinite), a traceback;
    # a TCP 1e300 mm or 150 m from the flange, or turned 1e300°, passed
    ("program.movej.vel", 10 ** 400), ("plan.acc", 10 ** 400), ("robot.tcp", {"x150": {"xyz_mm": [10 ** 400, 0, 0]}}),
    ("robot.tcp", {"x150": {"xyz_mm": [0, 0, 0], "rxyz_deg": [0, -10 ** 400, 0]}}),
    ("robot.tcp", {"x150": {"xyz_mm": [1e300, 0, 0]}}), ("robot.tcp", {"x150": {"xyz_mm": [150000, 0, 0]}}),
    ("robot.tcp", {"x150": {"xyz_mm": [0, 0, 0], "rxyz_deg": [1e300, 0, 0]}}),
    ("robot.tcp", {"x150": {"xyz_mm": [0, 0, 0], "rxyz_deg": [0, 0, 360.5]}}),
    ("ingest.sep", "|"), ("ingest.skip_lines", -1), ("ingest.decimal", ";"), ("ingest.length_unit", "cm"),
])
def test_a_bad_value_of_a_reviewed_key_stops_naming_it(key, value):
    p = copy.deepcopy(PARAMS)
    *path, last = key.split(".")
    cfg = p
    for k in path:
        cfg = cfg[k]
    cfg[last] = value
    with pytest.raises(ParamsError, match=rf"^params.yaml {re.escape(key)}: .+, got "):
        section(p, path[0])


def test_a_tcp_out_of_bounds_is_named_and_one_within_them_passes():
    """The robot.tcp error names the point and its key (a review, 2026-12-06, evening: no bounds at all);
    2 m and a full turn are the limits."""
    p = copy.deepcopy(PARAMS)
    for tcp, said in (({"ok": {"xyz_mm": [150.0, 0, 0]}, "far": {"xyz_mm": [150000, 0, 0]}},
                       r"point far: xyz_mm \[150000, 0, 0\] is not 3 finite numbers within ±2000 mm; robot.tcp is "),
                      ({"turned": {"xyz_mm": [0, 0, 10], "rxyz_deg": [1e300, 0, 0]}},
                       r"point turned: rxyz_deg \[1e\+300, 0, 0\] is not 3 finite angles within ±360°")):
        p["robot"]["tcp"] = tcp
        with pytest.raises(ParamsError, match=rf"^params.yaml robot.tcp: {said}.*, got "):
            section(p, "robot")
    p["robot"]["tcp"] = {"edge": {"xyz_mm": [2000, -2000.0, 0], "rxyz_deg": [360, -360.0, 0], "frame": "probe"}}
    assert section(p, "robot")["tcp"] == p["robot"]["tcp"]


@pytest.mark.parametrize("tcp, said", [
    ({"xyz_mm": [0, 0, 0.15]}, r"xyz_mm \[0, 0, 0.15\] is within 1 mm of the flange: metres\?"),
    ({"xyz_mm": [0, 0, 150], "rxyz_deg": [0, 1.5708, 0]}, r"rxyz_deg \[0, 1.5708, 0\] are right angles in radians\?"),
    ({"xyz_mm": [0, 0, 150], "rxyz_deg": [-3.1416, 0, 4.7124]}, r"rxyz_deg .* are right angles in radians\?"),
])
def test_a_tcp_copied_from_urs_set_tcp_in_metres_and_radians_is_refused(tcp, said):
    """A review (2026-12-06): `set_tcp(p[0, 0, 0.15, 0, 1.5708, 0])` copied as xyz_mm [0, 0, 0.15] and rxyz_deg
    [0, 1.5708, 0] was taken: every export, `--tcp` and TCP metric then for a point 0.15 mm off the flange,
    turned 1.57°. A tool at the flange (all 0) and one turned 90° or 1.5° still pass."""
    p = copy.deepcopy(PARAMS)
    p["robot"]["tcp"] = {"gun": tcp}
    with pytest.raises(ParamsError, match=rf"^params.yaml robot.tcp: point gun: {said}.* give .*, got "):
        section(p, "robot")
    for fine in ({"xyz_mm": [0, 0, 0]}, {"xyz_mm": [0, 0, 150], "rxyz_deg": [0, 90, 0]},
                 {"xyz_mm": [1.0, 0, 150], "rxyz_deg": [0, 1.5, 0]}, {"xyz_mm": [0, 0, 150], "rxyz_deg": [1.5708, 30, 0]}):
        p["robot"]["tcp"] = {"gun": fine}
        assert section(p, "robot")["tcp"] == {"gun": fine}


def test_a_campaign_too_small_for_every_split_stops_the_split_stage_naming_it(tmp_path, monkeypatch):
    """10 poses pass the ingest (at least 10), one frame outlier leaves 9: 8:1:1 gave train 8, val 1, test 0,
    and evaluate then stopped with a traceback (KeyError: 'test'). Now the split stage says why, in one line."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "data/interim").mkdir(parents=True)
    pd.DataFrame({"point_id": [f"P{i}" for i in range(9)], "campaign": "main",
                  **{f"j{j}_deg": np.arange(9.0) for j in range(1, 7)}}).to_parquet("data/interim/points.parquet")
    with pytest.raises(ValueError, match=r"campaign 'main': its 9 points split train 8, val 1, test 0 .* the "
                                         r"test split is empty"):
        split.run(copy.deepcopy(PARAMS))
    assert not (tmp_path / "data/interim/split.parquet").exists()


def test_a_pose_measured_again_is_never_split_across_train_and_test(tmp_path, monkeypatch):
    """IPA's Series_B measured 290 of its joint configurations twice (within 0.005°, re-measured 0.007-0.026 mm
    apart): drawn row by row, 55 of its 149 test points were poses also trained on. The split draws over
    poses (splits.repeats): here 40 of 200 random poses measured again 0.003° off all land in one split with
    their first measurement, and split.json counts them. A campaign without repeats keeps the paper's split."""
    from pipeline.lib.learning.splits import repeats, split_indices
    monkeypatch.chdir(tmp_path)
    (tmp_path / "data/interim").mkdir(parents=True)
    q = np.random.default_rng(3).uniform(-170, 170, (200, 6))
    again = np.vstack([q, q[:40] + 0.003])                             # rows 200..239 repeat rows 0..39
    for j, (name, joints) in enumerate((("plain", q), ("again", again))):
        pd.DataFrame({"point_id": [f"{name}{i}" for i in range(len(joints))], "campaign": "main",
                      **{f"j{k + 1}_deg": joints[:, k] for k in range(6)}}).to_parquet("data/interim/points.parquet")
        summary = split.run(copy.deepcopy(PARAMS))
        got = pd.read_parquet("data/interim/split.parquet").split.to_numpy()
        if name == "plain":                                            # the paper's split, row by row
            want = np.empty(200, object)
            for k, rows in split_indices(200, [0.8, 0.1, 0.1], 7).items():
                want[rows] = k
            assert (got == want).all() and summary["repeated_poses"] == {"main": {"rows": 0, "poses": 0}}
        else:
            assert (got[:40] == got[200:]).all(), np.flatnonzero(got[:40] != got[200:])
            assert summary["repeated_poses"] == {"main": {"rows": 80, "poses": 40}}
            assert sum(summary["counts"].values()) == 240 and set(got) == {"train", "val", "test"}
    assert (repeats(again)[200:] == np.arange(40)).all() and repeats(again).max() == 199
    few = np.vstack([q[:6], q[:6] + 0.003])                            # 12 rows, 6 poses: too few for 8:1:1
    pd.DataFrame({"point_id": [f"few{i}" for i in range(12)], "campaign": "main",
                  **{f"j{k + 1}_deg": few[:, k] for k in range(6)}}).to_parquet("data/interim/points.parquet")
    with pytest.raises(ValueError, match=r"its 12 points \(6 poses, the others measured again\) split"):
        split.run(copy.deepcopy(PARAMS))


def test_series_b_repeats_share_a_split():
    """The real Series_B (skipped where the public datasets are absent): 586 rows are 293 poses measured twice;
    none of its test points is a pose trained on, where row by row 56 were. (A review, 2026-12-06: at 0.01°
    three repeats, 0.010-0.013° apart, were two poses each, one in train and one in test or val; judged here
    on every pair of rows within 1°, which the grouping's own threshold does not decide.)"""
    from pipeline.lib.learning.splits import repeats, split_groups, split_indices
    table = Path(__file__).resolve().parents[2] / "shared/datasets/ipa-ur10/Series_B/measurements_joint_configurations.csv"
    if not table.exists():
        pytest.skip(f"dataset ipa-ur10 not present at {table}")
    joints = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
              "wrist_3_joint"]
    q = np.degrees(pd.read_csv(table, sep=";", decimal=",")[joints].to_numpy(float))
    g = repeats(q)
    sizes = np.bincount(g)
    assert len(q) == 1495 and sizes[sizes > 1].sum() == 586 and (sizes > 1).sum() == 293 and sizes.max() == 2
    pairs = cKDTree(q).query_pairs(1.0, p=np.inf, output_type="ndarray")   # the next distinct poses: 5.4° apart
    assert len(pairs) == 293

    def trained_in_test(idx):
        trained = set(g[idx["train"]])
        return sum(1 for r in idx["test"] if sizes[g[r]] > 1 and g[r] in trained)

    def straddling(idx):
        where = np.empty(len(q), object)
        for k, rows in idx.items():
            where[rows] = k
        return int((where[pairs[:, 0]] != where[pairs[:, 1]]).sum())
    assert trained_in_test(split_indices(len(q), [0.8, 0.1, 0.1], 7)) == 56
    assert trained_in_test(split_groups(g, [0.8, 0.1, 0.1], 7)) == 0 and straddling(split_groups(g, [0.8, 0.1, 0.1], 7)) == 0

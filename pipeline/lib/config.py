"""params.yaml (the one owner of every setting), JSON writing, logging.

`section(params, name)` hands a stage its section after checking the keys:
an unknown or misspelt key, or a missing one, stops the stage with a message
that lists the valid keys. The code never falls back to a default of its own.
"""
import json
import logging
import sys
from pathlib import Path

import numpy as np
import yaml

PARAMS = Path("params.yaml")

# The keys of every section (names only; the values live in params.yaml).
SECTIONS = {
    "robot": ("model", "dh", "joint_limits_deg", "tool_mm"),
    "ingest": ("joints", "tracker", "sep", "decimal", "angle_unit", "length_unit", "columns",
               "gross_outlier_mm"),
    "ingest.columns": ("point_id", "joints", "position"),
    "campaigns": ("name", "station", "more"),
    "campaigns.campaign": ("ingest", "station"),
    "frame": ("outlier_k", "outlier_min_mm", "estimate_tool", "tool_per_station", "robust_loss", "robust_scale_mm",
              "max_rms_mm"),
    "split": ("seed", "fractions", "holdout"),
    "split.holdout": ("joints", "quantile"),
    "calibrate": ("loss", "loss_scale_mm", "params", "tilt_joints", "rank_tol", "tol", "max_nfev"),
    "parts": ("noise_mm", "angle_map", "load_map", "thermal"),
    "parts.thermal": ("column", "cte_per_k"),
    "parts.angle_map": ("joints", "knot_deg", "prior_arcsec", "smooth_arcsec", "reach_deg", "fade_deg"),
    "parts.load_map": ("joints", "knots", "prior_arcsec", "smooth_arcsec"),
    "model": ("d_model", "n_layer", "n_head", "d_hidden", "mask", "head", "encoder", "physics",
              "alpha0", "dropout", "fade_to", "init_seed"),
    "loss": ("weighting", "physics", "lambda_data", "lambda_physics"),
    "train": ("lr", "weight_decay", "batch_size", "grad_clip", "max_epochs", "patience", "seed", "ema",
              "members", "lr_drop", "lr_patience", "device"),
    "baselines": ("dnn", "other_physics"),
    "workspace": ("radius_quantile", "coverage"),
    "validate": ("register_points", "tool_rank_tol", "campaigns"),
    "validate.campaign": ("ingest", "frame", "commanded"),
    "validate.commanded": ("columns", "unit", "rz_deg", "orientation", "euler", "planned_tool_mm"),
    "compensate": ("solver", "lr", "max_iter", "tol_mse", "tol_mm", "jacobian_of", "drive_check",
                   "twin", "drive_seed"),
    "ablation": ("seeds", "max_epochs"),
    "plan": ("cover_k", "per_waypoint", "region", "region_margin_deg", "seed", "rules", "settle_s", "handshake_io",
             "acc", "vel"),
    "plan.rules": ("radius_mm", "height_mm", "elbow_up", "elbow_min_mm", "table_mm", "column_mm", "sin_elbow",
                   "sin_wrist", "tracker_side_deg"),
    "serve": ("host", "port", "unreachable_mm", "onnx", "torch_threads", "compile", "max_iter", "budget_ms", "stall_iter",
              "stall_ratio", "max_batch", "batch_wait_ms", "max_items", "max_body_bytes", "timeout_s", "echo_chars"),
}


OPTIONAL = ("holdout",)        # nested sections that may be null (off)


class ParamsError(ValueError):
    """A params.yaml section with an unknown, misspelt or missing key."""


def check_keys(cfg, name: str) -> dict:
    """cfg (the section `name`, e.g. "ingest.columns") if its keys are exactly SECTIONS[name]."""
    valid = SECTIONS[name]
    if not isinstance(cfg, dict):
        raise ParamsError(f"params.yaml {name}: expected a mapping with keys {list(valid)}, got {cfg!r}")
    unknown = [k for k in cfg if k not in valid]
    missing = [k for k in valid if k not in cfg]
    if unknown or missing:
        what = "; ".join(([f"unknown key(s) {unknown}"] if unknown else [])
                         + ([f"missing key(s) {missing}"] if missing else []))
        raise ParamsError(f"params.yaml {name}: {what}. Valid keys: {', '.join(valid)}")
    return cfg


def section(params: dict, name: str) -> dict:
    """params[name], its keys checked (and those of its nested sections)."""
    if name not in params:
        raise ParamsError(f"params.yaml: missing section {name!r} (keys: {', '.join(SECTIONS[name])})")
    cfg = check_keys(params[name], name)
    for sub in SECTIONS:                               # nested sections (not validate.campaign / campaigns.campaign: one per entry)
        key = sub.split(".", 1)[1] if sub.startswith(name + ".") else None
        if key in SECTIONS[name] and not (key in OPTIONAL and cfg[key] is None):
            check_keys(cfg[key], sub)
    return cfg


def sections(params: dict, *names: str) -> list[dict]:
    """The sections `names`, each checked by `section`."""
    return [section(params, n) for n in names]


def for_stage(params: dict, names) -> dict:
    """Only the sections `names` of params (each checked): what a stage may read. A stage declares
    them in its module's PARAMS, and tests/test_layout.py holds dvc.yaml's `params:` to the same list,
    so a setting a stage reads is always one that re-runs it."""
    return {n: section(params, n) for n in names}


def load_params(path: Path | str = PARAMS) -> dict:
    with open(path) as f:
        return yaml.safe_load(f)


def _jsonable(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON-serialisable: {type(o)}")


def write_json(path: Path | str, obj) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2, default=_jsonable) + "\n")


TIMING_KEYS = ("seconds", "seconds_per_epoch", "ms_per_point")   # wall-clock: never in a hashed output


def split_timings(obj):
    """(obj without its TIMING_KEYS, those values in the same nesting): a stage writes the first to
    its DVC-hashed summary and the second to reports/timings/, so the same params and seed give the
    same bytes however busy the machine was."""
    if not isinstance(obj, dict):
        if isinstance(obj, list):
            pairs = [split_timings(v) for v in obj]
            return [a for a, _ in pairs], [b for _, b in pairs]
        return obj, None
    kept, times = {}, {}
    for k, v in obj.items():
        if k in TIMING_KEYS:
            times[k] = v
            continue
        kept[k], t = split_timings(v)
        if t not in (None, {}, []) and not (isinstance(t, list) and not any(t)):
            times[k] = t
    return kept, times


def read_json(path: Path | str):
    return json.loads(Path(path).read_text())


def logger(name: str) -> logging.Logger:
    """A stage's logger, named after its module even when run as `python -m pipeline.<stage>`."""
    if name == "__main__":
        spec = getattr(sys.modules["__main__"], "__spec__", None)
        name = spec.name if spec else name
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s",
                        datefmt="%H:%M:%S")
    return logging.getLogger(name.removeprefix("pipeline.").removeprefix("lib."))

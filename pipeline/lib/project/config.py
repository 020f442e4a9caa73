"""params.yaml (the one owner of every setting), JSON writing, logging.

`section(params, name)` hands a stage its section after checking the keys:
an unknown or misspelt key, or a missing one, stops the stage with a message
that lists the valid keys. The code never falls back to a default of its own.
"""
import io
import json
import logging
import math
import re
import sys
from pathlib import Path

import numpy as np

from pipeline.lib.project.artifacts import PARAMS_FILE
from pipeline.lib.project.writing import write_file

# The keys of every section (names only; the values live in params.yaml).
SECTIONS = {
    "robot": ("model", "dh", "joint_limits_deg", "tool_mm", "tcp"),
    "ingest": ("joints", "tracker", "skip_lines", "sep", "decimal", "angle_unit", "length_unit", "columns",
               "gross_outlier_mm", "orientation", "target", "target_residual_mm"),
    "ingest.columns": ("point_id", "joints", "position", "orientation", "marker"),
    "ingest.orientation": ("kind", "sequence", "angle_unit", "scalar_first"),
    "campaigns": ("name", "station", "more"),
    "campaigns.campaign": ("ingest", "station"),
    "frame": ("outlier_k", "outlier_min_mm", "estimate_tool", "tool_per_station", "robust_loss", "robust_scale_mm",
              "max_rms_mm", "max_orientation_scatter_arcsec"),
    "split": ("seed", "fractions", "holdout"),
    "split.holdout": ("joints", "quantile"),
    "calibrate": ("loss", "loss_scale_mm", "params", "tilt_joints", "pose_noise", "rank_tol", "tol", "max_nfev"),
    "calibrate.pose_noise": ("mm", "arcsec"),
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
    "validate": ("register_points", "tool_rank_tol", "tool_significance", "campaigns"),
    "validate.campaign": ("ingest", "frame", "commanded"),
    "validate.commanded": ("columns", "unit", "rz_deg", "orientation", "euler", "planned_tool_mm"),
    "compensate": ("solver", "lr", "max_iter", "tol_mse", "tol_mm", "tol_arcsec", "orientation", "jacobian_of",
                   "physics_steps", "drive_check", "twin", "drive_seed"),
    "ablation": ("seeds", "max_epochs"),
    "summary": ("instrument",),
    "program": ("move", "movej", "movel"),
    "program.movej": ("acc", "vel"),
    "program.movel": ("acc", "vel"),
    "plan": ("cover_k", "per_waypoint", "region", "region_margin_deg", "seed", "rules", "settle_s", "handshake_io",
             "acc", "vel"),
    "plan.rules": ("radius_mm", "height_mm", "elbow_up", "elbow_min_mm", "table_mm", "column_mm", "sin_elbow",
                   "sin_wrist", "tracker_side_deg"),
    "path": ("spacing_mm", "chord_mm", "speed_mm_s", "accel_mm_s2", "corner_mm", "max_deviation_mm",
             "joint_speed_deg_s", "max_samples", "lookahead_s", "gain"),
    "serve": ("host", "port", "unreachable_mm", "onnx", "torch_threads", "compile", "max_iter", "budget_ms", "stall_iter",
              "stall_ratio", "max_batch", "batch_wait_ms", "max_items", "call_budget_ms", "lm_per_call", "max_body_bytes", "timeout_s",
              "max_connections", "echo_chars", "max_path_samples", "refusal_delay_ms"),
}


OPTIONAL = ("holdout",)        # nested sections that may be null (off)


# The allowed values of the settings a typo in would otherwise surface deep in NumPy, torch or a server
# thread: "section.key" -> (check, what it must be). Checked with the keys, by `section`.
def _int(lo, hi=None):
    return lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= lo and (hi is None or v <= hi)


def real(x) -> bool:
    """x is a finite number (no text, no boolean; an integer too large for a float, 400 digits, is not one)."""
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, float, np.integer, np.floating)):
        return False
    try:
        return bool(np.isfinite(float(x)))
    except OverflowError:
        return False


def _num(lo, hi=None, open_lo=False):
    return lambda v: real(v) and (v > lo if open_lo else v >= lo) and (hi is None or v <= hi)


def _scripted(hi: float, unit: str, what: str) -> tuple:
    """The rule of a robot script's motion setting: SCRIPTED to hi (a slip of unit beyond it), in unit."""
    return _num(SCRIPTED, hi), f"{what} {SCRIPTED:g}-{hi:.4g} {unit} (the script writes 6 decimals; more is a slip of unit)"


def _fractions(v):
    return (isinstance(v, list) and len(v) == 3 and all(_num(0, 1, open_lo=True)(x) for x in v)
            and abs(sum(v) - 1) < 1e-9)


def _speeds(v):
    return v is None or _num(0, open_lo=True)(v) or (isinstance(v, list) and len(v) == 6
                                                      and all(_num(0, open_lo=True)(x) for x in v))


def _joints(v):
    return isinstance(v, list) and len(v) > 0 and all(_int(1, 6)(j) for j in v) and len(set(v)) == len(v)


def _headers(*counts):
    """null, or a list of `counts` headers, distinct as the reader matches them (case and spaces ignored)."""
    return lambda v: v is None or (isinstance(v, list) and len(v) in counts and all(map(_header, v))
                                   and len({str(h).strip().lower() for h in v}) == len(v))


def _vec3(v, bound=math.inf):
    """3 finite numbers, each within ±bound."""
    return isinstance(v, list) and len(v) == 3 and all(_num(-bound, bound)(x) for x in v)


def tcp_problem(v) -> str | None:
    """What is wrong with `robot.tcp` (naming the point and its key), or None: null, or name: {xyz_mm (each
    within ±OFFSET_MM_MAX, not all within 1 mm unless all 0: metres), rxyz_deg (optional, each within ±360°,
    its turns not all right angles in radians), frame (optional, flange or probe)}."""
    if v is None:
        return None
    if not isinstance(v, dict) or not v:
        return "not a mapping of names"
    for k, t in v.items():
        if not (isinstance(k, str) and re.fullmatch(r"[A-Za-z0-9_-]{1,40}", k)) or k == "marker":
            return f"the name {k!r} is not allowed"
        if not isinstance(t, dict) or not set(t) <= {"xyz_mm", "rxyz_deg", "frame"}:
            return f"point {k}: not a mapping of xyz_mm, rxyz_deg, frame"
        if not _vec3(t.get("xyz_mm"), OFFSET_MM_MAX):
            return f"point {k}: xyz_mm {t.get('xyz_mm')!r} is not 3 finite numbers within ±{OFFSET_MM_MAX:g} mm"
        if not _vec3(t.get("rxyz_deg", [0, 0, 0]), 360.0):
            return f"point {k}: rxyz_deg {t.get('rxyz_deg')!r} is not 3 finite angles within ±360°"
        if 0 < max(map(abs, t["xyz_mm"])) < 1.0:
            return (f"point {k}: xyz_mm {t['xyz_mm']!r} is within 1 mm of the flange: metres? (UR's set_tcp is in m "
                    "and rad): give it in mm")
        turned = [abs(a) for a in t.get("rxyz_deg", []) if a]
        if turned and all(min(abs(a - r) for r in RIGHT_ANGLES_RAD) < 1e-3 for a in turned):
            return (f"point {k}: rxyz_deg {t['rxyz_deg']!r} are right angles in radians? (UR's set_tcp is in m and "
                    "rad, its turn a rotation vector): give the xyz Euler angles in degrees")
        if t.get("frame", "flange") not in ("flange", "probe"):
            return f"point {k}: frame {t.get('frame')!r} is neither flange nor probe"
    return None


def _bool(v):
    return isinstance(v, bool)


def _one_of(*choices):
    return lambda v: isinstance(v, str) and v in choices


def _or_null(ok):
    return lambda v: v is None or ok(v)


def _lt(lo, hi):
    """A number in [lo, hi) (finite)."""
    return lambda v: _num(lo, hi)(v) and v < hi


def _open(lo, hi):
    """A number in (lo, hi) (finite)."""
    return lambda v: _lt(lo, hi)(v) and v > lo


def _interval(lo, hi):
    """[a, b] with lo <= a < b <= hi."""
    return lambda v: isinstance(v, list) and len(v) == 2 and all(_num(lo, hi)(x) for x in v) and v[0] < v[1]


def _sequence(v) -> bool:
    """Three Euler axes as scipy's Rotation.from_euler reads them: all upper (intrinsic) or all lower (extrinsic)
    case, no axis twice in a row."""
    return (isinstance(v, str) and len(v) == 3 and (set(v) <= set("XYZ") or set(v) <= set("xyz"))
            and v[0] != v[1] and v[1] != v[2])


def _text(v) -> bool:
    """Some text: a path, a host."""
    return isinstance(v, str) and v.strip() != ""


def _header(v):
    """A column header as a setting names one: text or a number, not blank."""
    return isinstance(v, (str, int)) and not isinstance(v, bool) and str(v).strip() != ""


# The choices some settings take, declared here once (the code that uses them imports them).
LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")          # scipy.optimize.least_squares' `loss`
CALIBRATION_GROUPS = ("d", "a", "alpha", "offset", "beta", "tool", "base", "compliance", "tool_rot")
MASKS = ("spi", "body", "none")
HEADS = ("resnet", "linear")
WEIGHTINGS = ("paper", "uncertainty", "fixed")
DEVICES = ("auto", "cpu", "cuda")
SOLVERS = ("lm", "adam")
REACH_MM = 5000.0          # a plan.rules length beyond this is a typo (the largest UR reaches 1750 mm)
POS = _num(0, open_lo=True)
SCRIPTED = 1e-3              # a robot script's setting, written with 6 decimals: 3 significant digits at least
# Upper bounds of a robot script's motion settings: far above what a measurement or compensated move wants,
# at or above what any arm in robots.py can do, so that a value beyond one is a slip of unit or decimal point
# (deg/s as rad/s, mm/s as m/s) and stops the command; the robot's safety configuration keeps the last word.
JOINT_SPEED_MAX = 2 * math.pi   # rad/s: 360 deg/s, the fastest joint in robots.py (the e-series' wrists)
JOINT_ACC_MAX = 40.0            # rad/s²
TOOL_SPEED_MAX = 5.0            # m/s: the highest tool speed limit UR's safety configuration takes
TOOL_ACC_MAX = 15.0             # m/s²
SETTLE_MAX_S = 3600.0           # plan.settle_s: an hour a pose (URScript's 32-bit float holds it to the ms)
MAX_DEVIATION_MM = 10.0         # path.max_deviation_mm: a branch flip between two samples is tens of mm
RIGHT_ANGLES_RAD = (math.pi / 2, math.pi, 3 * math.pi / 2, 2 * math.pi)   # a tool's usual turns, written in radians
OFFSET_MM_MAX = 2000.0          # robot.tool_mm's and robot.tcp's xyz_mm, each: over 2 m from the flange, a slip of unit

RULES = {
    "robot.tcp": (lambda v: tcp_problem(v) is None,
                  lambda v: f"{tcp_problem(v)}; robot.tcp is null, or name: {{xyz_mm: [x, y, z] each within "
                  f"±{OFFSET_MM_MAX:g} mm, rxyz_deg: [rx, ry, rz] each within ±360°, frame: flange or probe}} (a tool "
                  "centre point in the flange frame, or measured in the probe's; rxyz_deg and frame optional), names "
                  "of letters, digits, _ or - (not marker: the probe's own, in ur_calibration.yaml's tool_frames)"),
    "calibrate.pose_noise.mm": (_num(0, open_lo=True), "a position noise > 0 mm"),
    "calibrate.pose_noise.arcsec": (_num(0, open_lo=True), "an orientation noise > 0 arcsec"),
    "split.seed": (_int(0), "an integer >= 0"),
    "split.fractions": (_fractions, "three fractions > 0 (train, val, test) that sum to 1"),
    "split.holdout.joints": (_joints, "a list of distinct joint numbers 1-6"),
    "split.holdout.quantile": (_num(0, 1, open_lo=True), "a quantile in (0, 1]"),
    "train.batch_size": (_int(1), "an integer >= 1"),
    "train.max_epochs": (_int(1), "an integer >= 1"),
    "train.patience": (_int(1), "an integer >= 1"),
    "train.seed": (_int(0), "an integer >= 0"),
    "train.members": (_int(1), "an integer >= 1"),
    "train.lr": (_num(0, open_lo=True), "a learning rate > 0"),
    "compensate.max_iter": (_int(1), "an integer >= 1"),
    "compensate.tol_mm": (_num(0, open_lo=True), "a tolerance > 0 mm"),
    "compensate.physics_steps": (_int(1, 20), "an integer 1-20"),
    "compensate.tol_arcsec": (_num(0, open_lo=True), "a tolerance > 0 arcsec"),
    "compensate.orientation": (lambda v: isinstance(v, bool), "true or false"),
    "program.move": (lambda v: v in ("movej", "movel"), "movej or movel"),
    "program.movej.acc": _scripted(JOINT_ACC_MAX, "rad/s²", "an acceleration"),
    "program.movej.vel": _scripted(JOINT_SPEED_MAX, "rad/s", "a speed"),
    "program.movel.acc": _scripted(TOOL_ACC_MAX, "m/s²", "an acceleration"),
    "program.movel.vel": _scripted(TOOL_SPEED_MAX, "m/s", "a speed"),
    "path.spacing_mm": (_num(0, open_lo=True), "a spacing > 0 mm"),
    "path.chord_mm": (lambda v: v is None or _num(0, open_lo=True)(v), "null or a tolerance > 0 mm"),
    "path.speed_mm_s": (_num(0, 1000 * TOOL_SPEED_MAX, open_lo=True), f"a speed > 0 mm/s, at most {1000 * TOOL_SPEED_MAX:g}"),
    "path.accel_mm_s2": (_num(1, 1000 * TOOL_ACC_MAX), f"an acceleration 1-{1000 * TOOL_ACC_MAX:g} mm/s²"),
    "path.corner_mm": (_num(0, 1, open_lo=True), "a distance in (0, 1] mm"),
    "path.max_deviation_mm": (_num(0, MAX_DEVIATION_MM, open_lo=True),
                              f"a distance > 0 mm, at most {MAX_DEVIATION_MM:g} (beyond, a branch flip passes)"),
    "path.joint_speed_deg_s": (_speeds, "null (the robot's), a speed > 0 deg/s or 6 of them"),
    "path.max_samples": (_int(2), "an integer >= 2"),
    "path.lookahead_s": (_num(0.03, 0.2), "servoj's lookahead_time, 0.03-0.2 s"),
    "path.gain": (_int(100, 2000), "servoj's gain, an integer 100-2000"),
    "serve.port": (_int(0, 65535), "a TCP port 0-65535 (0: any free port)"),
    "serve.torch_threads": (_int(1), "an integer >= 1"),
    "serve.unreachable_mm": (_num(0, open_lo=True), "a distance > 0 mm"),
    "serve.max_iter": (_int(1), "an integer >= 1"),
    "serve.budget_ms": (_num(0, open_lo=True), "a time > 0 ms"),
    "serve.stall_iter": (_int(1), "an integer >= 1"),
    "serve.stall_ratio": (_num(0, 1, open_lo=True), "a ratio in (0, 1]"),
    "serve.max_batch": (_int(1), "an integer >= 1"),
    "serve.batch_wait_ms": (_num(0), "a time >= 0 ms"),
    "serve.max_items": (_int(1), "an integer >= 1"),
    "serve.max_body_bytes": (_int(1), "an integer >= 1"),
    "serve.timeout_s": (_num(0, open_lo=True), "a time > 0 s"),
    "serve.echo_chars": (_int(20), "an integer >= 20"),
    "serve.refusal_delay_ms": (_num(0, 1000), "a time in 0..1000 ms"),
    "ingest.joints": (_text, "the path of the controller log"),
    "ingest.tracker": (_text, "the path of the tracker export"),
    "ingest.skip_lines": (_int(0), "a whole number of lines >= 0"),
    "ingest.sep": (lambda v: v in ("auto", ",", ";", "\t", "tab", "\\t"), "auto, ',', ';' or tab"),
    "ingest.decimal": (lambda v: v in ("auto", ".", ","), "auto, '.' or ','"),
    "ingest.angle_unit": (lambda v: v in ("deg", "rad"), "deg or rad"),
    "ingest.length_unit": (lambda v: v in ("mm", "m"), "mm or m"),
    "ingest.columns.point_id": (lambda v: v is None or _header(v) or (isinstance(v, list) and len(v) == 2
                                                                      and all(map(_header, v))),
                                "null (auto), a header, or [joints file's header, tracker file's header]"),
    "ingest.columns.joints": (_headers(6), "null (auto) or 6 headers, distinct ignoring case and spaces"),
    "ingest.columns.position": (_headers(3), "null (auto) or 3 headers, distinct ignoring case and spaces"),
    "ingest.columns.orientation": (_headers(3, 4, 9), "null, or 3 (Euler angles), 4 (quaternion) or 9 (rotation "
                                   "matrix, row-major) headers, distinct ignoring case and spaces"),
    "ingest.columns.marker": (_or_null(_header), "null, or the header naming each row's marker"),
    "ingest.orientation.kind": (lambda v: v in ("euler", "quaternion", "matrix"), "euler, quaternion or matrix"),
    "ingest.orientation.sequence": (_sequence,
                                    "three axes as scipy's Rotation.from_euler: XYZ, ZYX, ZXZ, ... upper case intrinsic "
                                    "(about the turning probe's axes), lower case extrinsic (about the tracker's); "
                                    "no axis twice in a row, no mixed case"),
    "ingest.orientation.angle_unit": (lambda v: v in ("deg", "rad"), "deg or rad"),
    "ingest.orientation.scalar_first": (lambda v: isinstance(v, bool), "true (w x y z) or false (x y z w)"),
    "ingest.target": (lambda v: v is None or (isinstance(v, dict) and set(v) == {"markers"} and isinstance(v["markers"], dict)
                                              and len(v["markers"]) >= 3 and all(isinstance(k, (str, int)) and _vec3(p)
                                                                                 for k, p in v["markers"].items())),
                      "null (estimated from the poses), or {markers: {name: [x, y, z] mm}} with at least 3 markers"),
    "ingest.target_residual_mm": (_num(0, open_lo=True), "a distance > 0 mm"),
    "ingest.gross_outlier_mm": (_or_null(POS), "null (off) or a distance > 0 mm"),
    "serve.max_path_samples": (_int(2), "an integer >= 2"),
    "model.d_model": (_int(1), "an integer >= 1"),
    "model.n_layer": (_int(1), "an integer >= 1"),
    "model.n_head": (_int(1), "an integer >= 1"),
    "model.d_hidden": (_int(1), "an integer >= 1"),
    "model.fade_to": (lambda v: v is None or _num(1, open_lo=True)(v), "null or a number of workspace radii > 1"),
    "model.physics": (lambda v: v in ("nominal", "calibrated"), "nominal or calibrated"),
    "compensate.jacobian_of": (lambda v: v in ("physics", "model"), "physics or model"),
    "calibrate.tilt_joints": (lambda v: v == [] or _joints(v), "a list of distinct joint numbers 1-6 (or [])"),
    "plan.handshake_io": (lambda v: v is None or _int(0, 7)(v), "null or a standard digital I/O number 0-7"),
    "plan.cover_k": (_int(1), "an integer >= 1 (planned poses per uncovered part)"),
    "plan.per_waypoint": (_int(1), "an integer >= 1 (candidates per waypoint, the waypoint included)"),
    "plan.region": (_int(0), "an integer >= 0 (candidates sampled in the program's joint box)"),
    "plan.region_margin_deg": (_num(0, 360), "an angle 0-360 deg"),
    "plan.seed": (_int(0), "an integer >= 0"),
    "plan.settle_s": (_num(SCRIPTED, SETTLE_MAX_S), f"a time 0.001-{SETTLE_MAX_S:g} s (the script writes 6 decimals)"),
    "plan.acc": _scripted(JOINT_ACC_MAX, "rad/s²", "an acceleration"),
    "plan.vel": _scripted(JOINT_SPEED_MAX, "rad/s", "a speed"),
    "plan.rules.radius_mm": (_or_null(_interval(0, REACH_MM)), f"null (off) or [lo, hi] mm, 0 <= lo < hi <= {REACH_MM:g}"),
    "plan.rules.height_mm": (_or_null(_interval(-REACH_MM, REACH_MM)),
                             f"null (off) or [lo, hi] mm, -{REACH_MM:g} <= lo < hi <= {REACH_MM:g}"),
    "plan.rules.elbow_up": (_or_null(_bool), "null (off), true or false"),
    "plan.rules.elbow_min_mm": (_or_null(_num(-REACH_MM, REACH_MM)), f"null (off) or a height within ±{REACH_MM:g} mm"),
    "plan.rules.table_mm": (_or_null(_num(-REACH_MM, REACH_MM)), f"null (off) or a height within ±{REACH_MM:g} mm"),
    "plan.rules.column_mm": (_or_null(_num(0, REACH_MM)), f"null (off) or a distance 0-{REACH_MM:g} mm"),
    "plan.rules.sin_elbow": (_or_null(_lt(0, 1)), "null (off) or a number in [0, 1)"),
    "plan.rules.sin_wrist": (_or_null(_lt(0, 1)), "null (off) or a number in [0, 1)"),
    "plan.rules.tracker_side_deg": (_or_null(_num(0, 180, open_lo=True)), "null (off) or an angle in (0, 180] deg"),
    "frame.outlier_k": (POS, "a number > 0 (of 1.4826 MAD)"),
    "frame.outlier_min_mm": (_num(0), "a distance >= 0 mm"),
    "frame.estimate_tool": (_bool, "true or false"),
    "frame.tool_per_station": (_bool, "true or false"),
    "frame.robust_loss": (_one_of(*LOSSES), ", ".join(LOSSES)),
    "frame.robust_scale_mm": (POS, "a distance > 0 mm"),
    "frame.max_rms_mm": (POS, "a distance > 0 mm"),
    "frame.max_orientation_scatter_arcsec": (POS, "an angle > 0 arcsec"),
    "calibrate.loss": (_one_of(*LOSSES), ", ".join(LOSSES)),
    "calibrate.loss_scale_mm": (POS, "a distance > 0 mm"),
    "calibrate.params": (lambda v: isinstance(v, list) and len(v) > 0 and len(set(map(str, v))) == len(v)
                         and all(isinstance(g, str) and g in CALIBRATION_GROUPS for g in v),
                         f"a non-empty list of distinct groups of {', '.join(CALIBRATION_GROUPS)}"),
    "calibrate.rank_tol": (_open(0, 1), "a relative singular value in (0, 1)"),
    "calibrate.tol": (_num(0, 1, open_lo=True), "a tolerance in (0, 1]"),
    "calibrate.max_nfev": (_int(1), "an integer >= 1"),
    "parts.noise_mm": (POS, "a noise > 0 mm"),
    "parts.angle_map.joints": (lambda v: v == [] or _joints(v), "[] (off) or a list of distinct joint numbers 1-6"),
    "parts.angle_map.knot_deg": (_num(0.1, 90), "a knot spacing 0.1-90 deg"),
    "parts.angle_map.prior_arcsec": (POS, "a prior > 0 arcsec"),
    "parts.angle_map.smooth_arcsec": (POS, "a prior > 0 arcsec"),
    "parts.angle_map.reach_deg": (_num(0, 360), "an angle 0-360 deg"),
    "parts.angle_map.fade_deg": (_num(0, 360, open_lo=True), "an angle in (0, 360] deg"),
    "parts.load_map.joints": (lambda v: v == [] or _joints(v), "[] (off) or a list of distinct joint numbers 1-6"),
    "parts.load_map.knots": (_int(2), "an integer >= 2"),
    "parts.load_map.prior_arcsec": (POS, "a prior > 0 arcsec"),
    "parts.load_map.smooth_arcsec": (POS, "a prior > 0 arcsec"),
    "parts.thermal.column": (_or_null(_header), "null or the ingest table's temperature column"),
    "parts.thermal.cte_per_k": (_num(-1e-3, 1e-3), "an expansion coefficient per K within ±0.001 (aluminium 2.3e-5)"),
    "model.mask": (_one_of(*MASKS), " | ".join(MASKS)),
    "model.head": (_one_of(*HEADS), " | ".join(HEADS)),
    "model.encoder": (_bool, "true or false"),
    "model.alpha0": (_num(-math.inf), "a finite number"),
    "model.dropout": (_lt(0, 1), "a probability in [0, 1)"),
    "model.init_seed": (_int(0), "an integer >= 0"),
    "loss.weighting": (_one_of(*WEIGHTINGS), " | ".join(WEIGHTINGS)),
    "loss.physics": (_bool, "true or false"),
    "loss.lambda_data": (POS, "a weight > 0"),
    "loss.lambda_physics": (POS, "a weight > 0"),
    "train.weight_decay": (_num(0), "a number >= 0"),
    "train.grad_clip": (POS, "a gradient norm > 0"),
    "train.ema": (_or_null(_lt(0, 1)), "null (off) or a decay in [0, 1)"),
    "train.lr_drop": (_or_null(_open(0, 1)), "null (off) or a factor in (0, 1)"),
    "train.lr_patience": (_int(0), "an integer >= 0"),
    "train.device": (lambda v: v in DEVICES or (isinstance(v, str) and re.fullmatch(r"cuda:\d+", v) is not None),
                     " | ".join(DEVICES) + " (or cuda:N)"),
    "baselines.dnn": (_bool, "true or false"),
    "baselines.other_physics": (_bool, "true or false"),
    "workspace.radius_quantile": (_num(0, 1, open_lo=True), "a quantile in (0, 1]"),
    "workspace.coverage": (_num(0, 1, open_lo=True), "a quantile in (0, 1]"),
    "validate.commanded.columns": (lambda v: v is not None and _headers(3)(v), "3 headers of the commanded TCP "
                                   "position, distinct ignoring case and spaces"),
    "validate.commanded.unit": (lambda v: v in ("mm", "m"), "mm or m"),
    "validate.commanded.rz_deg": (_num(-360, 360), "an angle -360..360 deg (a UR's: 180)"),
    "validate.commanded.orientation": (_headers(3), "null, or 3 headers of the commanded orientation (rad)"),
    "validate.commanded.euler": (_sequence, "three axes as scipy's Rotation.from_euler: xyz (extrinsic), XYZ "
                                 "(intrinsic), ..."),
    "validate.commanded.planned_tool_mm": (_vec3, "[x, y, z] mm: the TCP the command was planned for"),
    "validate.register_points": (_int(3), "an integer >= 3"),
    "validate.tool_rank_tol": (_open(0, 1), "a relative pivot in (0, 1)"),
    "validate.tool_significance": (_num(0), "a number of standard errors >= 0 (0: keep every determined component)"),
    "compensate.solver": (_one_of(*SOLVERS), " | ".join(SOLVERS)),
    "compensate.lr": (POS, "a learning rate > 0"),
    "compensate.tol_mse": (POS, "a tolerance > 0 mm²"),
    "compensate.drive_check": (_bool, "true or false"),
    "compensate.twin": (_text, "a file path"),
    "compensate.drive_seed": (_int(0), "an integer >= 0"),
    "ablation.seeds": (lambda v: isinstance(v, list) and len(v) > 0 and all(_int(0)(s) for s in v)
                       and len(set(v)) == len(v), "a non-empty list of distinct integers >= 0"),
    "ablation.max_epochs": (_or_null(_int(1)), "null (train.max_epochs) or an integer >= 1"),
    "summary.instrument": (_or_null(lambda v: isinstance(v, str)), "null or a text"),
    "serve.host": (_text, "a host name or address (127.0.0.1, 0.0.0.0)"),
    "serve.onnx": (_bool, "true or false"),
    "serve.compile": (_bool, "true or false"),
    "serve.call_budget_ms": (POS, "a time > 0 ms"),
    "serve.lm_per_call": (_int(1), "an integer >= 1"),
    "serve.max_connections": (_int(1), "an integer >= 1"),
}


class ParamsError(ValueError):
    """A params.yaml section with an unknown, misspelt or missing key."""


def check_keys(cfg, name: str, shown: str | None = None, partial: bool = False) -> dict:
    """cfg (the section `name`, e.g. "ingest.columns") if its keys are exactly SECTIONS[name] (partial: some of
    them); a ParamsError names it as `shown` (where it was given; default `name`)."""
    valid, shown = SECTIONS[name], shown or name
    if not isinstance(cfg, dict):
        raise ParamsError(f"params.yaml {shown}: expected a mapping with {'some of the ' if partial else ''}keys "
                          f"{list(valid)}, got {cfg!r}")
    unknown = [k for k in cfg if k not in valid]
    missing = [] if partial else [k for k in valid if k not in cfg]
    if unknown or missing:
        what = "; ".join(([f"unknown key(s) {unknown}"] if unknown else [])
                         + ([f"missing key(s) {missing}"] if missing else []))
        raise ParamsError(f"params.yaml {shown}: {what}. Valid keys: {', '.join(valid)}")
    return cfg


def check_values(cfg: dict, name: str, shown: str | None = None) -> None:
    """A ParamsError naming the key (as `shown`.key; default the section's own) for a value of the section
    `name` that breaks its RULES (a rule's text may be a function of the value, to name what in it is wrong);
    keys cfg does not hold are not checked."""
    for key, (ok, what) in RULES.items():
        path = key.split(".")
        if ".".join(path[:-1]) != name or path[-1] not in cfg:
            continue
        v = cfg[path[-1]]
        if not ok(v):
            text = what(v) if callable(what) else what
            raise ParamsError(f"params.yaml {shown or name}.{path[-1]}: {text}, got {v!r}")


def check_given(cfg, name: str, shown: str) -> None:
    """Some keys of the section `name` (a campaign's override of the ingest section), each known and its value
    within RULES, nested sections too; a ParamsError names the key where it was given, `shown`.key
    (campaigns.more.b.ingest.sep)."""
    check_values(check_keys(cfg, name, shown, partial=True), name, shown)
    for k, v in cfg.items():
        if f"{name}.{k}" in SECTIONS:
            check_given(v, f"{name}.{k}", f"{shown}.{k}")


def section(params: dict, name: str) -> dict:
    """params[name], its keys checked (and those of its nested sections), and their values (RULES)."""
    if not isinstance(params, dict):
        raise ParamsError(f"params.yaml: expected a mapping of sections, got {params!r}")
    if name not in params:
        raise ParamsError(f"params.yaml: missing section {name!r} (keys: {', '.join(SECTIONS[name])})")
    cfg = check_keys(params[name], name)
    check_values(cfg, name)
    for sub in SECTIONS:                               # nested sections (not validate.campaign / campaigns.campaign: one per entry)
        key = sub.split(".", 1)[1] if sub.startswith(name + ".") else None
        if key in SECTIONS[name] and not (key in OPTIONAL and cfg[key] is None):
            check_keys(cfg[key], sub)
            check_values(cfg[key], sub)
    return cfg


def sections(params: dict, *names: str) -> list[dict]:
    """The sections `names`, each checked by `section`."""
    return [section(params, n) for n in names]


def for_stage(params: dict, names) -> dict:
    """Only the sections `names` of params (each checked): what a stage may read. A stage declares
    them in its module's PARAMS, and tests/test_layout.py holds dvc.yaml's `params:` to the same list,
    so a setting a stage reads is always one that re-runs it."""
    return {n: section(params, n) for n in names}


def yaml_values(text: str, where: str):
    """YAML text read as DVC reads params.yaml (ruamel.yaml's safe loader, YAML 1.2: `1e-4` a number, `No` and
    `on` strings), so that a stage sees the values dvc.lock and `dvc exp show` record; a key given twice in one
    mapping (YAML would keep the last) or text that is not YAML a ParamsError naming `where` and the line."""
    from ruamel.yaml import YAML
    from ruamel.yaml.constructor import DuplicateKeyError
    from ruamel.yaml.error import MarkedYAMLError, YAMLError
    try:
        return YAML(typ="safe").load(text)
    except DuplicateKeyError as e:
        key = re.match(r'found duplicate key "(.*)" with value', e.problem or "")
        raise ParamsError(f"{where} line {e.problem_mark.line + 1}: the key {key[1] if key else '?'!r} is "
                          "given twice in one section (one would silently win)") from None
    except YAMLError as e:
        line = f" line {e.problem_mark.line + 1}" if isinstance(e, MarkedYAMLError) and e.problem_mark else ""
        raise ParamsError(f"{where}{line}: not YAML: {getattr(e, 'problem', None) or e}") from None


def yaml_text(obj) -> str:
    """obj as YAML that `yaml_values` (and DVC) read back as the same values: ruamel.yaml's safe dumper (a string
    PyYAML leaves bare, as '1e3' or '0o17', which YAML 1.2 reads as a number, is quoted), block style, keys in
    their order."""
    from ruamel.yaml import YAML
    y = YAML(typ="safe", pure=True)
    y.default_flow_style = False
    y.representer.sort_base_mapping_type_on_output = False
    buf = io.StringIO()
    y.dump(obj, buf)
    return buf.getvalue()


def load_params(path: Path | str = PARAMS_FILE) -> dict:
    """params.yaml as a dict of sections (each section's keys and values are checked by `section`), read as DVC
    reads it (`yaml_values`)."""
    params = yaml_values(Path(path).read_text(), str(path))
    if not isinstance(params, dict):
        raise ParamsError(f"{path}: expected a mapping of sections ({', '.join(s for s in SECTIONS if '.' not in s)}), "
                          f"got {'an empty file' if params is None else repr(params)[:80]}")
    return params


def _jsonable(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON-serialisable: {type(o)}")


def json_text(obj) -> str:
    """obj as the project's JSON files hold it (indented, numpy values as Python's)."""
    return json.dumps(obj, indent=2, default=_jsonable) + "\n"


def write_json(path: Path | str, obj) -> None:
    """obj as JSON (json_text) at path, whole or not at all."""
    write_file(path, json_text(obj))


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


LOG_FORMAT = ("%(asctime)s %(name)s: %(message)s", "%H:%M:%S")     # a log line: logging.Formatter(fmt, datefmt)


def logger(name: str) -> logging.Logger:
    """A stage's logger, named after its module even when run as `python -m pipeline.stages.<stage>`."""
    if name == "__main__":
        spec = getattr(sys.modules["__main__"], "__spec__", None)
        name = spec.name if spec else name
    logging.basicConfig(level=logging.INFO, format=LOG_FORMAT[0], datefmt=LOG_FORMAT[1])
    short = name.removeprefix("pipeline.").removeprefix("stages.").removeprefix("commands.")
    return logging.getLogger(short.split(".", 2)[2] if short.startswith("lib.") else short)   # lib.robot.x -> x

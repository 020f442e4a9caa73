"""Stage validate: judge nominal DH, the classical calibration and the model on independent campaigns.

    python -m pipeline.stages.validate campaign NAME   dvc stage validate@NAME (foreach validate.campaigns)
    python -m pipeline.stages.validate summary         dvc stage validation: every campaign in one file

A campaign is read by the ingest rules (lib/reading/readers.py, bad rows listed,
fatal errors naming file, row and column) with its own `ingest` overrides,
and judged `same` or `refit` (lib/learning/validation.py). A campaign the twin made (its files' SHA-256 in
`compensate.twin`'s record) is judged only when the robot was calibrated on the twin's campaign too;
otherwise it is listed under "skipped" with the reason, never read. Writes
reports/validation/NAME.json and .parquet; the summary stage writes
reports/validation.json and reports/validation.parquet (docs/data-format.md), an
empty summary when there are no campaigns, and reports/validation_headline.json (each campaign's
mean 3D error per method, for `dvc metrics show` and `dvc exp show`).
"""
import argparse
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from scipy.spatial.transform import Rotation

from pipeline.lib.learning.checkpoint import load_model
from pipeline.lib.learning.model import predict, served
from pipeline.lib.learning.validation import (METHODS, coverage, judge, judge_poses, orientation_percentiles,
                                              position_accuracy, summary)
from pipeline.lib.learning.workspace import Workspace
from pipeline.lib.project.artifacts import (CALIBRATED_GEOMETRY, FRAME_JSON, HERE, INGEST_JSON,
                                            MODEL_WEIGHTS, PARAMS_FILE, PARTS_JSON, VALIDATION_DIR,
                                            VALIDATION_HEADLINE, VALIDATION_JSON, VALIDATION_TABLE,
                                            WORKSPACE_JSON, as_given, rooted, rooted_files)
from pipeline.lib.project.cli import script
from pipeline.lib.project.columns import JOINTS_DEG, MEAS
from pipeline.lib.project.config import (check_keys, check_values, for_stage, load_params, logger, read_json,
                                         write_json)
from pipeline.lib.project.writing import remove_stale
from pipeline.lib.reading.campaigns import ingested_sha256, made_by_twin, named_campaign, pair_sha256, with_override
from pipeline.lib.reading.readers import ingest
from pipeline.lib.robot.errormaps import angle_covered
from pipeline.lib.robot.frames import MISREAD_PERCENTILE, DegenerateFit, FrameFitError, measured_rotations
from pipeline.lib.robot.geometry import Calibration, at_temperature, theory_geometry, with_parts
from pipeline.lib.robot.identify import orientation_weight
from pipeline.lib.robot.kinematics import DTYPE, TOOL_ROT, fk_numpy, fk_pose, flange_rotations
from pipeline.lib.robot.robots import load_robot
from pipeline.lib.robot.tcp import probe_offsets

log = logger(__name__)
TO_MM = {"mm": 1.0, "m": 1000.0}          # validate.campaigns.*.commanded.unit
PARAMS = {"campaign": ("robot", "ingest", "frame", "calibrate", "validate", "compensate"),      # validate@NAME
          "summary": ("validate",)}                                # validation


def commanded_positions(df: pd.DataFrame, spec: dict, tool_mm, name: str) -> np.ndarray:
    """Where the marker was commanded to be, (n, 3) mm in the DH base frame.

    The campaign commands a TCP (`columns`, in `unit`) planned with `planned_tool_mm`; the marker
    sits at the frame stage's tool_mm instead, so with the commanded orientation (`orientation`
    columns, radians, scipy Euler `euler`) the marker's commanded position is
    c + R (tool - planned_tool). The controller's base frame is the DH base turned by `rz_deg`
    about z (180 on a UR).
    """
    cols = spec["columns"] + (spec["orientation"] or [])
    missing = [c for c in cols if c not in df.columns]
    if missing:
        raise ValueError(f"params.yaml validate.campaigns.{name}.commanded: column(s) {missing} not in the "
                         f"campaign; it has {list(df.columns)}")
    c = df[spec["columns"]].to_numpy(float) * TO_MM[spec["unit"]]
    if spec["orientation"]:
        R = Rotation.from_euler(spec["euler"], df[spec["orientation"]].to_numpy(float)).as_matrix()
        c = c + np.einsum("nij,j->ni", R, np.asarray(tool_mm, float) - np.asarray(spec["planned_tool_mm"], float))
    return c @ Rotation.from_euler("z", spec["rz_deg"], degrees=True).as_matrix().T


def thermal_change(df: pd.DataFrame, parts: dict) -> dict | None:
    """The campaign's mean temperature against the training campaigns' (the parts stage's thermal
    reference), where both were recorded: {"column", "temperature_c", "temperature_ref_c", "dT_k",
    "cte_per_k"}; None otherwise."""
    th = parts.get("thermal")
    if not th or th["column"] not in df:
        return None
    T = float(df[th["column"]].mean())
    return {**th, "temperature_c": T, "dT_k": T - th["temperature_ref_c"]}


def per_joint_coverage(ws: Workspace, q: np.ndarray, table: pd.DataFrame) -> dict:
    """Per mapped joint: the share of judged points whose angle of that joint its map covers, and each
    method's mean error on them: what each joint's map can add where it holds."""
    if ws.angle_cover is None:
        return {}
    judged = ~table.registered.to_numpy()
    covered = angle_covered(ws.angle_cover, q)                                 # (n, 6)
    out = {}
    for j in np.flatnonzero(ws.angle_cover.any(1)):
        m = judged & covered[:, j]
        out[f"j{j + 1}"] = {"share": float(m.sum() / max(judged.sum(), 1)),
                            **{k: (float(table.loc[m, f"error_{k}_mm"].mean()) if m.any() else None)
                               for k in ("calibrated", "calibrated_parts", "model")}}
    return out


def twin_only(name: str, c: dict, twin_json: str, root: Path) -> str | None:
    """Why campaign `name` is not judged, or None: the twin made it (its files' SHA-256 are in the twin's
    record) but not the campaign trained on (ingest.json `files`), so it says nothing of this robot."""
    path = Path(rooted(root, twin_json))
    if not path.exists():                            # no twin here: it made nothing
        return None
    record = read_json(path)
    joints, tracker = c["ingest"]["joints"], c["ingest"]["tracker"]
    if made_by_twin(record, pair_sha256(rooted(root, joints), rooted(root, tracker))) is None:
        return None
    if made_by_twin(record, ingested_sha256(read_json(root / INGEST_JSON)["files"])) is not None:
        return None
    return (f"validate.campaigns.{name} is the twin's campaign ({joints}, {tracker}; {twin_json}) and the robot "
            "was calibrated on another: not judged (remove it from validate.campaigns to silence this)")


def training_target(cfg: dict, trained: dict, name: str) -> dict:
    """A validation campaign's ingest settings (cfg) whose multi-marker target's geometry would be estimated from
    its own poses (ingest.target: null), with the training campaign's instead (`trained`, its reports/ingest.json),
    so that the campaign's target frame is the one the model was trained in. Stops where the training campaign
    measured orientation without a target (no geometry to share)."""
    if "target" in trained:
        log.info("validate.campaigns.%s: the target's geometry is the training campaign's (%s)", name,
                 trained["target"]["geometry"])
        return {**cfg, "target": {"markers": trained["target"]["markers_mm"]}}
    if "orientation" in trained["units"]:
        raise ValueError(f"validate.campaigns.{name}.ingest: its multi-marker target's geometry would be estimated "
                         "from its own poses, whose frame is not the probe's the model was trained with (the training "
                         "campaign measured orientation without a target); give it in ingest.target")
    return cfg


def misread(at: dict, name: str, limit: float) -> None:
    """Stop where even the best method's orientation error (arcsec over the judged points, at the
    MISREAD_PERCENTILE: validation.orientation_percentiles) is above `limit` (frame.max_orientation_scatter_arcsec):
    no arm's error turns its flange that far, misread orientation columns do. The frame stage's check of a
    training campaign, for a validation campaign, which no frame stage sees."""
    best = min(at, key=at.get)
    if at[best] > limit:
        raise FrameFitError(f"validate.campaigns.{name}: its measured orientations are {at[best]:.0f} arcsec "
                            f"({MISREAD_PERCENTILE}th percentile) from every method's, the best ({best}) included, "
                            "above "
                            f"frame.max_orientation_scatter_arcsec = {limit:g}: its orientation columns are misread. Check validate.campaigns.{name}.ingest."
                            "orientation (the Euler sequence, intrinsic XYZ or extrinsic xyz, and angle_unit; a "
                            "quaternion's scalar_first), or set its ingest.columns.orientation to null to judge "
                            "positions alone")


def run_campaign(params: dict, name: str, root: Path = HERE) -> dict:
    p = for_stage(params, PARAMS["campaign"])
    frame_cfg, cfg = p["frame"], p["validate"]
    c = named_campaign(cfg["campaigns"], name, "validate.campaigns", "validate.campaign")
    if c["commanded"] is not None:                   # before the campaign is read and judged
        check_values(check_keys(c["commanded"], "validate.commanded", f"validate.campaigns.{name}.commanded"),
                     "validate.commanded", f"validate.campaigns.{name}.commanded")
    skipped = twin_only(name, c, p["compensate"]["twin"], root)
    if skipped:                                      # before reading it: it may not fit the user's ingest settings
        (root / VALIDATION_DIR).mkdir(parents=True, exist_ok=True)
        empty_table().to_parquet(root / VALIDATION_DIR / f"{name}.parquet", index=False)
        write_json(root / VALIDATION_DIR / f"{name}.json", {"skipped": skipped})
        log.info("%s", skipped)
        return {"skipped": skipped}
    robot, frame = load_robot(p["robot"]), read_json(root / FRAME_JSON)
    cal, parts = Calibration.from_dict(read_json(root / CALIBRATED_GEOMETRY)), read_json(root / PARTS_JSON)
    cfg_in = with_override(p["ingest"], c["ingest"], f"validate.campaigns.{name}.ingest")
    if cfg_in["columns"]["marker"] is not None and cfg_in["target"] is None:
        cfg_in = training_target(cfg_in, read_json(root / INGEST_JSON), name)
    df, ingested = ingest(rooted_files(cfg_in, root), robot, f"validate.campaigns.{name}.ingest")
    ingested = as_given(ingested, cfg_in, root)
    q = df[JOINTS_DEG].to_numpy()
    model = load_model(root / MODEL_WEIGHTS)
    thermal = thermal_change(df, parts)
    geometries = {"nominal": theory_geometry(robot, frame["tool_mm"], frame.get("tool_rot")), "calibrated": cal.geometry,
                  "calibrated_parts": with_parts(cal.geometry, parts), "model": model.physics.geometry()}
    if thermal:                                      # the arm at the campaign's temperature (not the nominal table)
        geometries = {m: g if m == "nominal" else at_temperature(g, thermal["dT_k"], thermal["cte_per_k"])
                      for m, g in geometries.items()}
        model.physics.load_state_dict(geometries["model"])
    pred = {m: fk_numpy(q, robot, g) for m, g in geometries.items() if m != "model"}
    ws = Workspace.from_dict(read_json(root / WORKSPACE_JSON))
    pred["model"] = predict(served(model, ws.network), df)     # what the robot cell gets (evaluate's verdict)
    qt = torch.as_tensor(np.radians(q), dtype=DTYPE)
    with torch.no_grad():
        flange = {m: flange_rotations(qt, g).numpy() for m, g in geometries.items()}
        R_world = measured_rotations(df) if TOOL_ROT in cal.geometry else None    # where trained with orientation
        probe = None if R_world is None else {m: fk_pose(qt, g)[1].numpy() for m, g in geometries.items()}
    P = df[MEAS].to_numpy()
    try:
        errors, registered, frames = judge(pred, P, c["frame"], frame, cfg["register_points"], frame_cfg, flange,
                                           cfg["tool_rank_tol"], probe, R_world,
                                           orientation_weight(p["calibrate"]["pose_noise"]), cfg["tool_significance"])
    except (FrameFitError, DegenerateFit) as e:      # DegenerateFit: the registration points collinear
        raise FrameFitError(f"validate.campaigns.{name}: {e}") from None
    if registered.all():                             # refit: every point registers the frame, none is judged
        raise ValueError(f"validate.campaigns.{name}: all {len(df)} points of the campaign go to the "
                         f"{c['frame']} registration (validate.register_points = {cfg['register_points']}): none "
                         "is left to judge; measure more poses, lower validate.register_points, or use frame: same "
                         "if the tracker did not move")
    u0, inside = ws(q)
    u = np.sqrt(u0 ** 2 + frames["model"].get("registration_rms_mm", 0.0) ** 2)    # validation.py: the campaign's own
    table = pd.DataFrame({"point_id": df.point_id, "campaign": name, "registered": registered,
                          **{f"error_{m}_mm": errors[m] for m in METHODS},
                          "uncertainty_mm": u, "in_workspace": inside, "in_range_angle_map": ws.parts(q)["angle_map"]})
    out = summary(table, c["frame"])
    judged = ~registered                             # the training uncertainty alone: no part of it from this campaign
    out["uncertainty_coverage_training"] = coverage(errors["model"][judged], u0[judged], inside[judged])
    out["angle_map"]["per_joint"] = per_joint_coverage(ws, q, table)
    out["ingest"] = {k: ingested[k] for k in ("n_read", "n_kept", "dropped", "dropped_counts")}
    out["registration"] = {m: {"tool_offset_mm": f["tool_offset_mm"], "tool_held": f.get("tool_held"),
                               "tool_held_why": f.get("tool_held_why"), "rms_mm": f.get("registration_rms_mm")}
                           for m, f in frames.items()}
    out["thermal"] = thermal
    if R_world is not None:                          # the orientation and the tools, where measured
        out["pose"] = judge_poses(pred, probe, flange, frames, P, R_world, probe_offsets(p["robot"]["tcp"], cal.geometry),
                                  ~registered)
        misread(orientation_percentiles(probe, frames, R_world, ~registered), name,
                frame_cfg["max_orientation_scatter_arcsec"])
        for m, f in frames.items():
            if "probe_rotation" in f:
                out["registration"][m]["probe_rotation_arcsec"] = float(
                    Rotation.from_matrix(f["probe_rotation"]).magnitude() * 206264.806)
        r = out["pose"]["model"]
        log.info("%s: model orientation %.0f arcsec mean (p95 %.0f); TCP mean %s mm", name,
                 r["orientation"]["mean_arcsec"], r["orientation"]["p95_arcsec"],
                 {k: round(v["mean_mm"], 4) for k, v in r["tcp"].items()})
    if c["commanded"]:                               # each method's base frame, the marker back on the training tool
        measured = {m: (P - frames[m]["t"]) @ frames[m]["R"] - np.einsum("mij,j->mi", flange[m],
                                                                          frames[m]["tool_offset_mm"])
                    for m in METHODS}
        commanded = commanded_positions(df, c["commanded"], frame["tool_mm"], name)
        group = df[c["commanded"]["columns"]].to_numpy(float) * TO_MM[c["commanded"]["unit"]]   # the command, mm
        out["position_accuracy"] = position_accuracy(commanded, group, measured, pred, ~registered,
                                                     c["frame"] != "same")
    (root / VALIDATION_DIR).mkdir(parents=True, exist_ok=True)
    table.to_parquet(root / VALIDATION_DIR / f"{name}.parquet", index=False)
    write_json(root / VALIDATION_DIR / f"{name}.json", out)
    m = out["mean_3d_mm"]
    log.info("%s (%s frame): %d points, %d judged, %.0f%% in the trained workspace; mean 3D error "
             "nominal %.3f, calibrated %.3f, model %.3f mm; %d rows dropped at ingest", name, c["frame"],
             out["n"], out["n_judged"], 100 * out["in_workspace_share"], m["nominal"], m["calibrated"],
             m["model"], len(ingested["dropped"]))
    return out


def empty_table() -> pd.DataFrame:
    """A validation table with no rows, its columns typed."""
    return pd.DataFrame({"point_id": pd.Series(dtype=str), "campaign": pd.Series(dtype=str),
                         "registered": pd.Series(dtype=bool),
                         **{f"error_{m}_mm": pd.Series(dtype=float) for m in METHODS},
                         "uncertainty_mm": pd.Series(dtype=float), "in_workspace": pd.Series(dtype=bool),
                         "in_range_angle_map": pd.Series(dtype=bool)})


def run_summary(params: dict, root: Path = HERE) -> dict:
    """reports/validation.json and .parquet from the campaigns params.yaml lists now (those not judged
    under "skipped", with the reason)."""
    names = sorted(for_stage(params, PARAMS["summary"])["validate"]["campaigns"] or {})
    for f in remove_stale(root / VALIDATION_DIR, names, (".json", ".parquet")):
        log.info("removed %s: campaign %r is no longer in validate.campaigns", f, f.stem)
    each = {n: read_json(root / VALIDATION_DIR / f"{n}.json") for n in names}
    judged = [n for n in names if "skipped" not in each[n]]
    out = {"campaigns": {n: each[n] for n in judged}}
    if len(judged) < len(names):
        out["skipped"] = {n: each[n]["skipped"] for n in names if n not in judged}
    tables = [pd.read_parquet(root / VALIDATION_DIR / f"{n}.parquet") for n in judged]
    pd.concat(tables or [empty_table()], ignore_index=True).to_parquet(root / VALIDATION_TABLE, index=False)
    write_json(root / VALIDATION_JSON, out)
    write_json(root / VALIDATION_HEADLINE, {n: {"n_judged": c["n_judged"], "mean_3d_mm": c["mean_3d_mm"]}
                                     for n, c in out["campaigns"].items()})
    log.info("validation summary: %d campaign(s) %s", len(names), names)
    return out


def main(argv=None, root: Path = HERE):
    ap = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["campaign", "summary"])
    ap.add_argument("name", nargs="?", help="campaign name (with `campaign`)")
    a = ap.parse_args(argv)
    params = load_params(root / PARAMS_FILE)
    if a.what == "campaign":
        return run_campaign(params, a.name, root)
    else:
        return run_summary(params, root)


if __name__ == "__main__":
    script(__spec__.name, main)

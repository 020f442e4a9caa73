"""Stage parts: per-joint error maps on what the classical calibration leaves (lib/robot/errormaps.py).

The calibrate stage's elasto-geometric chain explains the geometry and the linear sag under
gravity; what it leaves has, on a real arm, a fine per-joint structure: each joint's angle error as
a function of its own angle (gears, encoders), and of the load it carries. Those maps are fitted
here on the train split's residual through the calibrated chain's Jacobian, checked on the val
split (a part that does not lower the validation error is switched off, and says so), and written
to models/parts.json; SPI-BoTER's physics branch carries them (model.physics: calibrated), and its
network learns what remains. reports/parts.json: each part's size, whether it holds, the error
per split with and without the maps, and how far each part could re-learn a calibration parameter
(the share of its displacement the calibration's own parameters explain).
"""
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import torch

from pipeline.lib.project.artifacts import (CALIBRATED_GEOMETRY, CALIBRATION_JSON, FRAME_JSON, HERE, INGEST_TABLE,
                                            PARTS_JSON, PARTS_REPORT, load_points)
from pipeline.lib.project.cli import script, stage_main
from pipeline.lib.project.columns import JOINTS_DEG, MEAS, SPLITS
from pipeline.lib.project.config import for_stage, logger, read_json, write_json
from pipeline.lib.robot import errormaps
from pipeline.lib.robot.frames import measured_rotations
from pipeline.lib.robot.geometry import Calibration, aligned, theory_geometry
from pipeline.lib.robot.identify import (corrected, errors_3d, geometry_jacobian, in_units,
                                         orientation_errors, orientation_weight)
from pipeline.lib.robot.kinematics import (DTYPE, angular_jacobian, fk, fk_jacobian, fk_pose,
                                           gravity_torques, rotation_error, save_geometry)
from pipeline.lib.robot.robots import load_robot

log = logger(__name__)
PARAMS = ("robot", "calibrate", "parts")


def relearned_share(contrib: np.ndarray, Jg: np.ndarray) -> float:
    """The share (0..1) of a part's displacement (3n,) that the calibration's parameters (columns of Jg)
    explain: 0 = nothing a DH, tilt, tool, base or compliance parameter could do, 1 = all of it."""
    if not contrib.any():
        return 0.0
    proj = Jg @ np.linalg.lstsq(Jg, contrib, rcond=None)[0]
    return float((proj @ proj) / (contrib @ contrib))


def thermal_reference(train: pd.DataFrame, cfg: dict, root: Path) -> dict | None:
    """The temperature the arm was calibrated at (the mean over the training points of the ingest
    table's `parts.thermal.column`), with its expansion coefficient; None without a column."""
    if cfg["column"] is None:
        return None
    have = pq.read_schema(root / INGEST_TABLE).names
    if cfg["column"] not in have:
        raise ValueError(f"params.yaml parts.thermal.column: {cfg['column']!r} is not a column of {INGEST_TABLE} "
                         f"(it has {', '.join(h for h in have if h != 'point_id')})")
    T = pd.read_parquet(root / INGEST_TABLE, columns=["point_id", cfg["column"]]).set_index("point_id")[cfg["column"]]
    T = T.reindex(train["point_id"]).astype(float)
    if T.isna().any():
        raise ValueError(f"params.yaml parts.thermal.column: {cfg['column']!r} has no value for "
                         f"{int(T.isna().sum())} training points (e.g. {T[T.isna()].index[0]})")
    return {"column": cfg["column"], "temperature_ref_c": float(T.mean()), "span_k": float(T.max() - T.min()),
            "cte_per_k": cfg["cte_per_k"]}


def chain_residual(q: torch.Tensor, g: dict, meas: np.ndarray, R_meas: np.ndarray | None, weight: float):
    """What the chain g leaves at poses q, with its Jacobian in the joint angles: r (n, 3) mm and J (n, 3, 6),
    or with measured orientations R_meas (n, 6) and (n, 6, 6): the weighted (mm/rad) orientation rows below
    (identify.residual_rows' layout, measured minus modelled)."""
    with torch.no_grad():
        p_g, J = (v.numpy() for v in fk_jacobian(q, g))
        if R_meas is None:
            return meas - p_g, J
        R_g = fk_pose(q, g)[1]
        e = rotation_error(torch.as_tensor(R_meas, dtype=DTYPE), R_g).numpy()
        Jw = angular_jacobian(q, g).numpy()
    return np.hstack([meas - p_g, weight * e]), np.concatenate([J, weight * Jw], 1)


def fit_parts(df: pd.DataFrame, g: dict, identified: list, cfg: dict, calibrate_cfg: dict, passes: int = 2):
    """The error maps and the corrections of the calibration's identified parameters, fitted jointly on
    df's train split (Gauss-Newton passes about the corrected geometry), on positions and, where the
    table has them, orientations. Returns (geometry with the maps, maps, report, {parameter: correction})."""
    tr = (df.split == "train").to_numpy()
    q_deg = df[JOINTS_DEG].to_numpy()[tr]
    q = torch.as_tensor(np.radians(q_deg), dtype=DTYPE)
    meas = df[MEAS].to_numpy()[tr]
    R_meas = measured_rotations(df[tr])
    weight = None if R_meas is None else orientation_weight(calibrate_cfg["pose_noise"])
    total = None
    for _ in range(passes):
        r, J = chain_residual(q, g, meas, R_meas, weight)
        with torch.no_grad():
            tau = gravity_torques(q, g).numpy()
        Jg, spec = geometry_jacobian(q, g, calibrate_cfg, identified, weight)
        maps, report, dx = errormaps.fit(q_deg, tau, J, r, cfg, Jg)
        g = corrected(g, spec, dx)
        total = dx if total is None else total + dx
    report["relearned_share"] = {}
    X, _ = errormaps.design(q_deg, tau, J, maps)
    Jall, _ = geometry_jacobian(q, g, calibrate_cfg, None, weight)
    o = 0
    for b in report["blocks"]:
        m = b["coefficients"]
        key = "amap_coef" if b["part"] == "angle_map" else "lmap_coef"
        b["relearned_share"] = relearned_share(X[:, o:o + m] @ np.asarray(maps[key][b["joint"] - 1]), Jall)
        o += m
    return {**g, **errormaps.as_geometry(maps)}, maps, report, in_units(spec, total)


def run(params: dict, root: Path = HERE) -> dict:
    p = for_stage(params, PARAMS)
    cal_json = read_json(root / CALIBRATED_GEOMETRY)
    cal = Calibration.from_dict(cal_json)
    nominal = theory_geometry(load_robot(p["robot"]), read_json(root / FRAME_JSON)["tool_mm"])
    df = aligned(load_points(root), cal, nominal)
    thermal = thermal_reference(df[df.split == "train"], p["parts"]["thermal"], root)    # before the fit: its errors
    g, maps, report, deltas = fit_parts(df, cal.geometry, cal_json["identified"], p["parts"], p["calibrate"])
    q_deg = df[JOINTS_DEG].to_numpy()
    q = torch.as_tensor(np.radians(q_deg), dtype=DTYPE)
    meas = df[MEAS].to_numpy()
    with torch.no_grad():
        p_cal, p_parts, tau = fk(q, cal.geometry).numpy(), fk(q, g).numpy(), gravity_torques(q, g).numpy()
    split = {s: (df.split == s).to_numpy() for s in SPLITS}
    report["splits"] = {s: {"n": int(m.sum()), "calibrated": errors_3d(p_cal[m], meas[m]),
                            "calibrated_parts": errors_3d(p_parts[m], meas[m])} for s, m in split.items() if m.any()}
    R_meas = measured_rotations(df)
    if R_meas is not None:                             # the orientation's error too, where measured
        R_cal, R_parts = (fk_pose(q, gg)[1].numpy() for gg in (cal.geometry, g))
        for s, m in split.items():
            if m.any():
                report["splits"][s]["calibrated"]["orientation"] = orientation_errors(R_cal[m], R_meas[m])
                report["splits"][s]["calibrated_parts"]["orientation"] = orientation_errors(R_parts[m], R_meas[m])
    val = report["splits"].get("val", report["splits"]["train"])
    report["enabled"] = bool(maps) and val["calibrated_parts"]["mean_mm"] < val["calibrated"]["mean_mm"]
    if maps and not report["enabled"]:
        log.info("the error maps do not lower the validation error (%.4f -> %.4f mm): switched off",
                 val["calibrated"]["mean_mm"], val["calibrated_parts"]["mean_mm"])
    se = {k: v["se"] for k, v in read_json(root / CALIBRATION_JSON)["estimates"].items()}
    report["calibration_corrections"] = {k: {"delta": v, "calibration_se": se.get(k)} for k, v in deltas.items()}
    report["in_range_share"] = {s: {k: float(v.mean()) for k, v in errormaps.in_range(q_deg[m], tau[m], maps).items()}
                                for s, m in split.items() if m.any()}
    report["thermal"] = thermal
    save_geometry(root / PARTS_JSON, g if report["enabled"] else cal.geometry,
                  {"enabled": report["enabled"], "thermal": report["thermal"],
                   "maps_units": "amap_coef, lmap_coef rad; amap_cover 0..1 per degree; lmap_lo, lmap_step N·m"})
    write_json(root / PARTS_REPORT, report)
    s = report["splits"]
    log.info("error maps (%d coefficients, %s): mean 3D error train %.4f -> %.4f, val %.4f -> %.4f mm; "
             "largest re-learned share %.3f", report["n_coefficients"], "on" if report["enabled"] else "off",
             s["train"]["calibrated"]["mean_mm"], s["train"]["calibrated_parts"]["mean_mm"],
             val["calibrated"]["mean_mm"], val["calibrated_parts"]["mean_mm"],
             max([b["relearned_share"] for b in report["blocks"]], default=0.0))
    for b in report["blocks"]:
        log.info("  %s J%d: rms %.1f arcsec, displacement rms %.4f mm, re-learned share %.3f", b["part"], b["joint"],
                 b["coef_rms_arcsec"], b["displacement_rms_mm"], b["relearned_share"])
    big = sorted(deltas.items(), key=lambda kv: -abs(kv[1] / se[kv[0]]) if se.get(kv[0]) else 0)[:5]
    log.info("  calibration parameters moved most (in their standard errors): %s",
             ", ".join(f"{k} {v:+.4g} ({v / se[k]:+.1f} se)" for k, v in big if se.get(k)))
    return report


main = stage_main(__spec__.name, __doc__, run)         # main(argv=None, root=HERE)

if __name__ == "__main__":
    script(__spec__.name, main)

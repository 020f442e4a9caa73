"""Stage evaluate: MAE/MSE/RMSE/R² per split and axis (eqs. 27-42) for the model and baselines.

reports/metrics.json holds the model's metrics at the top level per split
(docs/data-format.md), under "campaigns" every training campaign's 3D MAE/RMSE
per method and split, and, under "baselines", the same metrics for every
comparison method on the same splits:
    nominal_dh      nominal DH after the frame fit (what the robot does uncompensated)
    calibrated_dh   classical kinematic calibration (calibrate stage)
    dnn             the paper's DNN baseline (baselines stage)
    spi_boter_*     SPI-BoTER on nominal / calibrated physics
Also data/interim/predictions.parquet (every point's prediction, with the
model's `uncertainty_mm` and `in_workspace`), reports/baselines.md (the
test-split table) and models/workspace.json (lib/learning/workspace.py: the training
poses' coverage and the model's error scale, fitted on the validation split;
metrics.json["uncertainty"] says how often the actual error stayed within it).

The network is kept only where it lowers the validation split's mean 3D error against the model's
physics branch alone, as the parts stage keeps the error maps: metrics.json["reported"] says which
method is reported, served and exported (workspace.json "network"; model.served), and
reports/headline.json holds the few numbers `dvc metrics show` and `dvc exp show` compare.

Where the campaign measures the probe's orientation, metrics.json["pose"] holds per method and split
the flange orientation error (arcsec) and the position error at every `robot.tcp` point (lib/robot/tcp.py);
the model's orientation is its physics branch's (the network corrects the marker's position).
"""
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.lib.learning.checkpoint import load_model
from pipeline.lib.learning.metrics import split_metrics
from pipeline.lib.learning.model import PhysicsOnly
from pipeline.lib.learning.model import predict
from pipeline.lib.learning.workspace import Workspace
from pipeline.lib.project.artifacts import (BASELINES_MD, BASELINES_TABLE, HEADLINE_JSON, HERE, METRICS_JSON,
                                            MODEL_WEIGHTS, PREDICTIONS_TABLE, WORKSPACE_JSON)
from pipeline.lib.project.cli import script, stage_main
from pipeline.lib.project.columns import CAMPAIGN, JOINTS_DEG, MEAS, PRED, SPLITS, STATION, THEORY
from pipeline.lib.project.config import for_stage, logger, write_json
from pipeline.lib.reading.prepared import load_prepared
from pipeline.lib.robot.frames import measured_rotations
from pipeline.lib.robot.geometry import theory_geometry
from pipeline.lib.robot.tcp import pose_errors, pose_of, probe_offsets

log = logger(__name__)
PARAMS = ("robot", "workspace")


def markdown_table(baselines: dict, split: str = "test") -> str:
    """Methods x 3D/axis metrics on one split, as a markdown table."""
    rows = [f"| method ({split}) | 3D MAE mm | 3D RMSE mm | 3D R² | x MAE | y MAE | z MAE |",
            "|---|---|---|---|---|---|---|"]
    for name, m in baselines.items():
        s = m[split]
        r2 = "–" if s["3d"]["r2"] is None else f"{s['3d']['r2']:.4f}"       # one point: undefined
        rows.append(f"| {name} | {s['3d']['mae']:.4f} | {s['3d']['rmse']:.4f} | {r2} "
                    f"| {s['x']['mae']:.4f} | {s['y']['mae']:.4f} | {s['z']['mae']:.4f} |")
    return "\n".join(rows) + "\n"


def campaign_metrics(df: pd.DataFrame, methods: dict) -> dict:
    """Per training campaign: its station, and every method's 3D MAE and RMSE per split."""
    out = {}
    for c in df[CAMPAIGN].unique():
        m = (df[CAMPAIGN] == c).to_numpy()
        sub = df[m].reset_index(drop=True)
        out[c] = {"station": sub[STATION].iloc[0], "n": {s: int((sub.split == s).sum()) for s in SPLITS},
                  **{k: {s: {q: v["3d"][q] for q in ("mae", "rmse")} for s, v in split_metrics(sub, p[m]).items()}
                     for k, p in methods.items()}}
    return out


def campaign_table(campaigns: dict, split: str = "test") -> str:
    """Campaigns x methods, 3D MAE on one split, as a markdown table."""
    methods = [k for k in next(iter(campaigns.values())) if k not in ("station", "n")]
    rows = [f"| campaign (station), {split} 3D MAE mm | n | " + " | ".join(methods) + " |",
            "|---|---|" + "---|" * len(methods)]
    for c, v in campaigns.items():
        rows.append(f"| {c} ({v['station']}) | {v['n'][split]} | "
                    + " | ".join(f"{v[k][split]['mae']:.4f}" if split in v[k] else "-" for k in methods) + " |")
    return "\n".join(rows) + "\n"


def physics_method(physics: str, maps: bool) -> str:
    """The baseline that is the model's physics branch alone (model.PhysicsOnly)."""
    return "nominal_dh" if physics == "nominal" else "calibrated_parts" if maps else "calibrated_dh"


def headline(metrics: dict) -> dict:
    """The few numbers an experiment is compared by (reports/headline.json): the reported model and every
    method's 3D MAE on the val and test splits, and the reported model's test 3D MAE per campaign."""
    r = metrics["reported"]["method"]
    out = {"network_kept": metrics["reported"]["network"]}
    for s in ("val", "test"):
        if s in metrics["baselines"][r]:
            out[f"{s}_3d_mae_mm"] = {"reported": metrics["baselines"][r][s]["3d"]["mae"],
                                     **{k: v[s]["3d"]["mae"] for k, v in metrics["baselines"].items()}}
    out["campaigns"] = {c: {"test_3d_mae_mm": v[r]["test"]["mae"]} for c, v in metrics["campaigns"].items()
                        if "test" in v[r]}
    pose = metrics.get("pose", {}).get(r, {}).get("test")
    if pose:                                             # where orientation is measured
        out["test_orientation_arcsec"] = pose["orientation"]["mean_arcsec"]
        out["test_tcp_mm"] = {k: v["mean_mm"] for k, v in pose["tcp"].items()}
    return out


def pose_metrics(df: pd.DataFrame, R_meas: np.ndarray, geometries: dict, model_pred: tuple, tcp: dict | None,
                 calibrated: dict) -> dict:
    """Per method and split: marker, orientation and TCP errors (lib/robot/tcp.py) where orientation is measured.
    geometries: {method: geometry}; model_pred: (its name, positions, its physics geometry)."""
    q, p_meas = df[JOINTS_DEG].to_numpy(), df[MEAS].to_numpy()
    offsets = probe_offsets(tcp, calibrated)
    poses = {k: pose_of(q, g) for k, g in geometries.items()}
    name, pred, physics = model_pred
    poses[name] = (pred, pose_of(q, physics)[1])
    return {k: {s: pose_errors(p[m], R[m], p_meas[m], R_meas[m], offsets)
                for s in SPLITS if (m := (df.split == s).to_numpy()).any()} for k, (p, R) in poses.items()}


def run(params: dict, root: Path = HERE) -> dict:
    p = for_stage(params, PARAMS)
    cfg = p["workspace"]
    prep = load_prepared(p["robot"], root)
    df, frame, cal, parts = prep.points, prep.frame, prep.calibration, prep.parts
    model = load_model(root / MODEL_WEIGHTS)
    pred = predict(model, df)
    q = df[JOINTS_DEG].to_numpy()
    name = f"spi_boter_{model.config['physics']}"
    methods = {"nominal_dh": df[THEORY].to_numpy(), name: pred}
    base = df[["point_id"]].merge(pd.read_parquet(root / BASELINES_TABLE), on="point_id", how="left")
    for col in base.columns[1::3]:
        stem = col.removesuffix("_x")
        methods.setdefault(stem, base[[f"{stem}_{a}" for a in "xyz"]].to_numpy())
    errors = {k: np.linalg.norm(v - df[MEAS].to_numpy(), axis=1) for k, v in methods.items()}
    err, val = errors[name], (df.split == "val").to_numpy()
    physics = np.linalg.norm(predict(PhysicsOnly(model), df) - df[MEAS].to_numpy(), axis=1)
    network = bool(err[val].mean() < physics[val].mean())      # as the error maps: kept where it lowers val
    maps = {"model": err, "calibrated": errors["calibrated_dh"],
            "calibrated_parts": errors.get("calibrated_parts", errors["calibrated_dh"])}
    ws = Workspace.fit(q[(df.split == "train").to_numpy()], {k: v[val] for k, v in maps.items()}, cfg,
                       model.config["fade_to"], parts["geometry"].get("amap_cover") if parts["enabled"] else None,
                       network)
    write_json(root / WORKSPACE_JSON, ws.to_dict())
    out = df[["point_id", CAMPAIGN, STATION, "split"] + JOINTS_DEG + THEORY + MEAS].copy()
    out[PRED] = pred
    u, inside = ws(q)
    out["uncertainty_mm"], out["in_workspace"] = u, inside
    out["in_range_angle_map"] = ws.parts(q)["angle_map"]
    out.to_parquet(root / PREDICTIONS_TABLE, index=False)

    metrics = split_metrics(df, pred)
    metrics["baselines"] = {k: split_metrics(df, v) for k, v in methods.items()}
    metrics["model"] = name
    metrics["campaigns"] = campaign_metrics(df, methods)
    served_err = err if network else physics          # the model the robot cell gets, as u describes it
    metrics["uncertainty"] = {s: {"coverage": float((served_err[m] <= u[m]).mean()),
                                  "in_workspace_share": float(inside[m].mean()),
                                  "uncertainty_mm_mean": float(u[m].mean())}
                              for s in SPLITS if (m := (df.split == s).to_numpy()).any()}
    metrics["uncertainty"]["target_coverage"] = cfg["coverage"]
    reported = name if network else physics_method(model.config["physics"], parts["enabled"])
    metrics["reported"] = {"method": reported, "network": network,
                           "val_3d_mae_mm": {"with_network": float(err[val].mean()),
                                             "physics_alone": float(physics[val].mean())}}
    R_meas = measured_rotations(df)
    if R_meas is not None:
        geometries = {"nominal_dh": theory_geometry(prep.robot, frame["tool_mm"], frame["tool_rot"]),
                      "calibrated_dh": cal.geometry, "calibrated_parts": prep.calibrated}
        metrics["pose"] = pose_metrics(df, R_meas, geometries, (name, pred, model.physics.geometry()),
                                       p["robot"]["tcp"], cal.geometry)
        if df[CAMPAIGN].nunique() > 1:               # and per training campaign
            metrics["pose_campaigns"] = {
                c: pose_metrics(df[m].reset_index(drop=True), R_meas[m], geometries,
                                (name, pred[m], model.physics.geometry()), p["robot"]["tcp"], cal.geometry)
                for c in df[CAMPAIGN].unique() if (m := (df[CAMPAIGN] == c).to_numpy()).any()}
        r = metrics["pose"].get(reported, metrics["pose"][name]).get("test")
        if r:
            log.info("test split, %s: orientation %.0f arcsec mean (p95 %.0f); TCP mean %s mm", reported,
                     r["orientation"]["mean_arcsec"], r["orientation"]["p95_arcsec"],
                     {k: round(v["mean_mm"], 4) for k, v in r["tcp"].items()})
    write_json(root / METRICS_JSON, metrics)
    write_json(root / HEADLINE_JSON, headline(metrics))
    table = markdown_table(metrics["baselines"])
    if len(metrics["campaigns"]) > 1:
        table += "\n" + campaign_table(metrics["campaigns"])
    (root / BASELINES_MD).write_text(table)
    log.info("evaluated %s on %s points\n%s", name,
             {s: int((df.split == s).sum()) for s in SPLITS}, table)
    log.info("workspace: radius %.1f deg over joints %s; uncertainty %.4f (model), %.4f (calibration + error maps), "
             "%.4f mm (calibration); test: %.0f%% in the workspace, uncertainty covers the error on %.0f%% "
             "(target %.0f%%)", ws.radius, ws.to_dict()["joints"], ws.u0, ws.u_parts, ws.u_cal, 100 * metrics["uncertainty"].get("test", {}).get("in_workspace_share", np.nan),
             100 * metrics["uncertainty"].get("test", {}).get("coverage", np.nan), 100 * cfg["coverage"])
    return metrics


main = stage_main(__spec__.name, __doc__, run)         # main(argv=None, root=HERE)

if __name__ == "__main__":
    script(__spec__.name, main)

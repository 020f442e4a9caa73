"""Stage baselines: the comparison methods, on the same splits as the model.

    calibrated_dh        classical kinematic calibration alone (calibrate stage's geometry)
    calibrated_parts     that calibration with the per-joint error maps (parts stage), no network
                         (when the parts hold)
    dnn                  the paper's DNN baseline: an MLP from joint angles to the error
                         (opt-in: baselines.dnn)
    spi_boter_<other>    SPI-BoTER on the physics branch the main model does not use
                         (opt-in: baselines.other_physics)
The opt-in ones are the paper's comparison, one `-S` away; `bench real` trains them.

Writes data/interim/baselines.parquet (point_id, <name>_x, <name>_y, <name>_z)
for evaluate, and reports/baselines_train.json.
"""
from pathlib import Path

import pandas as pd

from pipeline.lib.learning.model import predict
from pipeline.lib.learning.training import train_boter, train_dnn
from pipeline.lib.project.artifacts import BASELINES_JSON, BASELINES_TABLE, HERE, TIMINGS
from pipeline.lib.project.cli import script, stage_main
from pipeline.lib.project.columns import JOINTS_DEG
from pipeline.lib.project.config import for_stage, logger, split_timings, write_json
from pipeline.lib.reading.prepared import load_prepared
from pipeline.lib.robot.geometry import physics_geometry
from pipeline.lib.robot.kinematics import fk_numpy

log = logger(__name__)
PARAMS = ("robot", "model", "loss", "train", "baselines", "workspace")


def run(params: dict, root: Path = HERE) -> dict:
    p = for_stage(params, PARAMS)
    cfg = p["baselines"]
    prep = load_prepared(p["robot"], root)
    df, nominal, parts, calibrated = prep.points, prep.nominal, prep.parts, prep.calibrated
    out, summary = pd.DataFrame({"point_id": df["point_id"]}), {}

    def add(name, pred):
        out[[f"{name}_{a}" for a in "xyz"]] = pred

    add("calibrated_dh", fk_numpy(df[JOINTS_DEG].to_numpy(), None, prep.calibration.geometry))
    if parts["enabled"]:                              # the calibration with the per-joint error maps, no network
        add("calibrated_parts", fk_numpy(df[JOINTS_DEG].to_numpy(), None, calibrated))
    if cfg["dnn"]:
        dnn, summary["dnn"] = train_dnn(df, nominal, p["model"], p["train"])
        add("dnn", predict(dnn.eval(), df))
    if cfg["other_physics"]:
        other = "calibrated" if p["model"]["physics"] == "nominal" else "nominal"
        model, summary[f"spi_boter_{other}"] = train_boter(
            df, physics_geometry(other, calibrated, nominal), {**p["model"], "physics": other}, p["loss"],
            p["train"], p["workspace"]["radius_quantile"])
        add(f"spi_boter_{other}", predict(model.eval(), df))
    out.to_parquet(root / BASELINES_TABLE, index=False)
    summary, timings = split_timings(summary)
    write_json(root / BASELINES_JSON, summary)
    write_json(root / TIMINGS / "baselines.json", timings)
    log.info("baselines on %d points: calibrated_dh%s", len(df),
             "".join(f", {k} (best val 3D MAE {v['best_val_mae_3d_mm']:.4f} mm at epoch {v['best_epoch']})"
                     for k, v in summary.items()))
    return summary


main = stage_main(__spec__.name, __doc__, run)         # main(argv=None, root=HERE)

if __name__ == "__main__":
    script(__spec__.name, main)

"""Stage baselines: the comparison methods, on the same splits as the model.

    calibrated_dh        classical kinematic calibration alone (calibrate stage's geometry)
    dnn                  the paper's DNN baseline: an MLP from joint angles to the error
                         (opt-in: baselines.dnn)
    spi_boter_<other>    SPI-BoTER on the physics branch the main model does not use
                         (opt-in: baselines.other_physics)
The opt-in ones are the paper's comparison, one `-S` away; `bench real` trains them.

Writes data/interim/baselines.parquet (point_id, <name>_x, <name>_y, <name>_z)
for evaluate, and reports/baselines_train.json.
"""
import copy

import pandas as pd

from .lib.artifacts import BASELINES_JSON, BASELINES_TABLE, load_points
from .lib.columns import JOINTS_DEG
from .lib.config import load_params, logger, section, sections, write_json
from .lib.geometry import aligned, physics_geometry
from .lib.kinematics import fk_numpy
from .lib.training import predict, train_boter, train_dnn

log = logger(__name__)


def run(params: dict) -> dict:
    sections(params, "robot", "model", "loss", "train", "workspace")
    cfg = section(params, "baselines")
    df = aligned(load_points(), params)
    out, summary = pd.DataFrame({"point_id": df["point_id"]}), {}

    def add(name, pred):
        out[[f"{name}_{a}" for a in "xyz"]] = pred

    add("calibrated_dh", fk_numpy(df[JOINTS_DEG].to_numpy(), None, physics_geometry(params, "calibrated")))
    if cfg["dnn"]:
        dnn, summary["dnn"] = train_dnn(params, df, physics_geometry(params, "nominal"))
        add("dnn", predict(dnn.eval(), df))
    if cfg["other_physics"]:
        other = "calibrated" if params["model"]["physics"] == "nominal" else "nominal"
        alt = copy.deepcopy(params)
        alt["model"]["physics"] = other
        model, summary[f"spi_boter_{other}"] = train_boter(alt, df, physics_geometry(params, other))
        add(f"spi_boter_{other}", predict(model.eval(), df))
    out.to_parquet(BASELINES_TABLE, index=False)
    write_json(BASELINES_JSON, summary)
    log.info("baselines on %d points: calibrated_dh%s", len(df),
             "".join(f", {k} (best val 3D MAE {v['best_val_mae_3d_mm']:.4f} mm at epoch {v['best_epoch']})"
                     for k, v in summary.items()))
    return summary


if __name__ == "__main__":
    run(load_params())

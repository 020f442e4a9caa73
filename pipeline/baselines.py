"""Stage baselines: the comparison methods, on the same splits as the model.

    calibrated_dh        classical kinematic calibration alone (calibrate stage's geometry)
    dnn                  the paper's DNN baseline: an MLP from joint angles to the error
    spi_boter_<other>    SPI-BoTER on the physics branch the main model does not use

Writes data/interim/baselines.parquet (point_id, <name>_x, <name>_y, <name>_z)
for evaluate, and reports/baselines_train.json.
"""
import copy

import pandas as pd

from .columns import JOINTS_DEG
from .config import BASELINES_TABLE, CALIBRATED_GEOMETRY, REPORTS, load_params, logger, write_json
from .evaluate import predict
from .kinematics import fk_numpy
from .train import load_points, train_boter, train_dnn

log = logger(__name__)


def run(params: dict) -> dict:
    from .calibrate import load_geometry
    df = load_points()
    out, summary = pd.DataFrame({"point_id": df["point_id"]}), {}

    def add(name, pred):
        out[[f"{name}_{a}" for a in "xyz"]] = pred

    add("calibrated_dh", fk_numpy(df[JOINTS_DEG].to_numpy(), None, load_geometry(CALIBRATED_GEOMETRY)))
    dnn, summary["dnn"] = train_dnn(params, df)
    add("dnn", predict(dnn.eval(), df))
    if params.get("baselines", {}).get("other_physics", True):
        other = "calibrated" if params["model"].get("physics", "nominal") == "nominal" else "nominal"
        alt = copy.deepcopy(params)
        alt["model"]["physics"] = other
        model, summary[f"spi_boter_{other}"] = train_boter(alt, df)
        add(f"spi_boter_{other}", predict(model.eval(), df))
    out.to_parquet(BASELINES_TABLE, index=False)
    write_json(REPORTS / "baselines_train.json", summary)
    log.info("baselines on %d points: %s", len(df),
             {k: f"best val 3D MAE {v['best_val_mae_3d_mm']:.4f} mm at epoch {v['best_epoch']}"
              for k, v in summary.items()})
    return summary


def main():
    run(load_params())


if __name__ == "__main__":
    main()

"""Stage evaluate: MAE/MSE/RMSE/R² per split and axis (eqs. 27-42) for the model and baselines.

reports/metrics.json holds the model's metrics at the top level per split
(DATA_FORMAT.md) and, under "baselines", the same metrics for every
comparison method on the same splits:
    nominal_dh      nominal DH after the frame fit (what the robot does uncompensated)
    calibrated_dh   classical kinematic calibration (calibrate stage)
    dnn             the paper's DNN baseline (baselines stage)
    spi_boter_*     SPI-BoTER on nominal / calibrated physics
"""
import numpy as np
import pandas as pd
import torch

from .columns import JOINTS_DEG, MEAS, PRED, THEORY
from .config import BASELINES_TABLE, PREDICTIONS_TABLE, REPORTS, load_params, logger, write_json
from .metrics import regression_metrics
from .split import SPLITS
from .train import load_model, load_points, tensors

log = logger(__name__)


@torch.no_grad()
def predict(model, df: pd.DataFrame, batch: int = 4096) -> np.ndarray:
    """Model predictions (n, 3) mm, base frame."""
    q, _ = tensors(df)
    return torch.cat([model(qb)[0] for qb in q.split(batch)]).numpy()


def split_metrics(df: pd.DataFrame, pred: np.ndarray) -> dict:
    """{split: metrics} of predictions `pred` (rows aligned with df)."""
    return {s: regression_metrics(pred[m], df.loc[m, MEAS].to_numpy(), df.loc[m, THEORY].to_numpy())
            for s in SPLITS if (m := (df.split == s).to_numpy()).any()}


def run(params: dict) -> dict:
    df = load_points()
    model = load_model(params)
    pred = predict(model, df)
    out = df[["point_id", "split"] + JOINTS_DEG + THEORY + MEAS].copy()
    out[PRED] = pred
    out.to_parquet(PREDICTIONS_TABLE, index=False)

    metrics = split_metrics(df, pred)
    name = f"spi_boter_{params['model'].get('physics', 'nominal')}"
    methods = {"nominal_dh": df[THEORY].to_numpy(), name: pred}
    if BASELINES_TABLE.exists():
        base = df[["point_id"]].merge(pd.read_parquet(BASELINES_TABLE), on="point_id", how="left")
        for col in base.columns[1::3]:
            stem = col.removesuffix("_x")
            methods.setdefault(stem, base[[f"{stem}_{a}" for a in "xyz"]].to_numpy())
    metrics["baselines"] = {k: split_metrics(df, v) for k, v in methods.items()}
    metrics["model"] = name
    write_json(REPORTS / "metrics.json", metrics)
    table = markdown_table(metrics["baselines"])
    (REPORTS / "baselines.md").write_text(table)
    log.info("evaluated %s on %s points\n%s", name,
             {s: int((df.split == s).sum()) for s in SPLITS}, table)
    return metrics


def markdown_table(baselines: dict, split: str = "test") -> str:
    """Methods x 3D/axis metrics on one split, as a markdown table."""
    rows = [f"| method ({split}) | 3D MAE mm | 3D RMSE mm | 3D R² | x MAE | y MAE | z MAE |",
            "|---|---|---|---|---|---|---|"]
    for name, m in baselines.items():
        s = m[split]
        rows.append(f"| {name} | {s['3d']['mae']:.4f} | {s['3d']['rmse']:.4f} | {s['3d']['r2']:.4f} "
                    f"| {s['x']['mae']:.4f} | {s['y']['mae']:.4f} | {s['z']['mae']:.4f} |")
    return "\n".join(rows) + "\n"


def main():
    run(load_params())


if __name__ == "__main__":
    main()

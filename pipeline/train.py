"""Stage train: fit SPI-BoTER (sec. 3.2) on the train split, early-stopped on val.

The physics branch is `model.physics` (calibrated: the calibrate stage's
geometry; nominal: the paper's). Per-epoch curves go to dvclive
(reports/live); weights to models/boter.pt as a state_dict; the summary to
reports/train.json.
"""
import torch
from dvclive import Live

from .lib.artifacts import LIVE, MODEL_WEIGHTS, TRAIN_JSON, load_points
from .lib.config import load_params, logger, sections, write_json
from .lib.geometry import aligned, physics_geometry
from .lib.training import train_boter

log = logger(__name__)


def run(params: dict) -> dict:
    sections(params, "robot", "model", "loss", "train", "workspace")
    df = aligned(load_points(), params)
    geometry = physics_geometry(params, params["model"]["physics"])
    with Live(dir=str(LIVE), save_dvc_exp=False, dvcyaml=False) as live:
        model, summary = train_boter(params, df, geometry, live)   # dvclive needs a git repo with a commit
    MODEL_WEIGHTS.parent.mkdir(parents=True, exist_ok=True)
    torch.save(model.state_dict(), MODEL_WEIGHTS)
    write_json(TRAIN_JSON, summary)
    log.info("trained SPI-BoTER (%d parameters) on %d points: best val 3D MAE %.4f mm at epoch "
             "%s of %d, %.1f s (%.3f s/epoch); alpha %s", summary["n_params"], summary["n_train"],
             summary["best_val_mae_3d_mm"], summary["best_epoch"], summary["epochs_run"],
             summary["seconds"], summary["seconds_per_epoch"], summary["alpha"])
    return summary


if __name__ == "__main__":
    run(load_params())

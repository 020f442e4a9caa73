"""Stage train: fit SPI-BoTER (sec. 3.2) on the train split, early-stopped on val.

The physics branch is `model.physics` (calibrated: the calibrate stage's
geometry; nominal: the paper's). Per-epoch curves go to dvclive
(reports/live); the checkpoint (weights and the `model:` section it was built
from) to models/boter.pt; the summary to reports/train.json, its wall-clock
times to reports/timings/train.json.
"""
from pathlib import Path

from dvclive import Live

from pipeline.lib.learning.checkpoint import save_model
from pipeline.lib.learning.model import check_config
from pipeline.lib.learning.training import resolve_device, train_boter
from pipeline.lib.project.artifacts import HERE, LIVE, MODEL_WEIGHTS, TIMINGS, TRAIN_JSON
from pipeline.lib.project.cli import script, stage_main
from pipeline.lib.project.config import for_stage, logger, split_timings, write_json
from pipeline.lib.reading.prepared import load_prepared
from pipeline.lib.robot.geometry import physics_geometry

log = logger(__name__)
PARAMS = ("robot", "model", "loss", "train", "workspace")


def run(params: dict, root: Path = HERE) -> dict:
    p = for_stage(params, PARAMS)
    check_config(p["model"])                       # before dvclive resets reports/live: a bad setting
    resolve_device(p["train"]["device"])           # leaves the last run's curves as they were
    prep = load_prepared(p["robot"], root)
    df = prep.points
    geometry = physics_geometry(p["model"]["physics"], prep.calibrated, prep.nominal)
    # save_dvc_exp: dvclive needs a git repo with a commit; no system monitor and no timestamps: the curves
    # are hashed in dvc.lock, so the same params give the same bytes (issue 21)
    with Live(dir=str(root / LIVE), save_dvc_exp=False, dvcyaml=False, report=None, monitor_system=False) as live:
        model, summary = train_boter(df, geometry, p["model"], p["loss"], p["train"],
                                     p["workspace"]["radius_quantile"], live)
    (root / MODEL_WEIGHTS).parent.mkdir(parents=True, exist_ok=True)
    save_model(model, root / MODEL_WEIGHTS, p["model"])
    summary, timings = split_timings(summary)
    write_json(root / TRAIN_JSON, summary)
    write_json(root / TIMINGS / "train.json", timings)
    log.info("trained SPI-BoTER (%d parameters) on %d points: best val 3D MAE %.4f mm at epoch "
             "%s of %d, %.1f s (%.3f s/epoch); alpha %s", summary["n_params"], summary["n_train"],
             summary["best_val_mae_3d_mm"], summary["best_epoch"], summary["epochs_run"],
             timings["seconds"], timings["seconds_per_epoch"], summary["alpha"])
    return summary


main = stage_main(__spec__.name, __doc__, run)         # main(argv=None, root=HERE)

if __name__ == "__main__":
    script(__spec__.name, main)

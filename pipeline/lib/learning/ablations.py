"""The ablation groups (the paper's sec. 4.2.3-4.2.4, and the loss weighting) and one training run
of a group at a seed: what `python -m pipeline.commands.ablation` and `bench sweep` run as jobs (lib/learning/sweep.py), each
job (Job) its settings, the data every job trains on (Data) shared: on Ray, in the object store once."""
import copy
from dataclasses import dataclass

import pandas as pd

from pipeline.lib.learning.metrics import split_metrics
from pipeline.lib.learning.model import predict
from pipeline.lib.learning.training import train_boter
from pipeline.lib.project.config import logger

log = logger(__name__)
GROUPS = {                                   # name -> params changes (one source of the groups)
    "baseline": {},
    "data_only": {"loss": {"physics": False}},
    "no_mask": {"model": {"mask": "none"}},
    "body_mask": {"model": {"mask": "body"}},
    "no_resnet": {"model": {"head": "linear"}},
    "no_transformer": {"model": {"encoder": False}},
    # not in the paper: docs/method.md's loss-weighting choice, measured the same way
    "paper_weights": {"loss": {"weighting": "paper"}},
    "fixed_weights": {"loss": {"weighting": "fixed"}},
}


@dataclass(repr=False)
class Job:
    """One training run: the sections model, loss, train, workspace and ablation, a group and a seed."""
    params: dict
    group: str
    seed: int

    def __repr__(self) -> str:                     # a failed run named by what tells it apart
        return f"{self.group} seed {self.seed}"


@dataclass
class Data:
    """What every run of a sweep trains on: the aligned points (with their split) and the physics
    geometries by `model.physics`. A sweep's `shared` value: on Ray, put once into the object store."""
    points: pd.DataFrame
    geometries: dict


def group_params(params: dict, group: str, seed: int) -> dict:
    p = copy.deepcopy(params)
    for name, changes in GROUPS[group].items():
        p[name].update(changes)
    p["model"]["init_seed"], p["train"]["seed"] = seed, seed
    p["train"]["max_epochs"] = params["ablation"]["max_epochs"] or p["train"]["max_epochs"]
    return p


def train_one(job: Job, data: Data) -> dict:
    """One (group, seed) training run on `data` (torch threads set by its sweep); returns its test
    metrics and epochs."""
    df, p = data.points, group_params(job.params, job.group, job.seed)
    model, hist = train_boter(df, data.geometries[p["model"]["physics"]], p["model"], p["loss"], p["train"],
                              p["workspace"]["radius_quantile"], progress=False)
    test = split_metrics(df, predict(model.eval(), df))["test"]
    log.info("%s seed %d: test 3D MAE %.4f mm, best epoch %d", job.group, job.seed, test["3d"]["mae"],
             hist["best_epoch"])
    return {"seed": job.seed, "test": test, "epochs_to_best": hist["best_epoch"],
            "epochs_run": hist["epochs_run"], "seconds": hist["seconds"], "n_params": hist["n_params"]}

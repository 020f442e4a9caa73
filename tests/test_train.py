"""Training: same params and seed give the same model on CPU; the best validation checkpoint is kept."""
import json

import numpy as np
import pandas as pd
import pytest
import torch

from pipeline.lib.columns import ERR, JOINTS_DEG, MEAS, THEORY
from pipeline.lib.kinematics import fk_numpy, nominal_geometry
from pipeline.lib.robots import load_robot
from pipeline.lib.training import mae_3d, tensors, train_boter

PARAMS = {
    "robot": {"model": "ur5", "tool_mm": [0.0, 0.0, 0.0], "dh": None, "joint_limits_deg": None},
    "model": {"d_model": 12, "n_layer": 1, "n_head": 2, "d_hidden": 16, "mask": "spi", "head": "resnet",
              "encoder": True, "physics": "nominal", "alpha0": 0.1, "dropout": 0.1, "fade_to": None, "init_seed": 3},
    "workspace": {"radius_quantile": 0.99, "coverage": 0.9},
    "loss": {"weighting": "uncertainty", "physics": True, "lambda_data": 1.0, "lambda_physics": 1.0},
    "train": {"lr": 1e-3, "weight_decay": 1e-6, "batch_size": 32, "grad_clip": 1.0, "max_epochs": 15,
              "patience": 5, "seed": 3, "ema": None, "members": 1,
              "lr_drop": None, "lr_patience": 40},
}
G = nominal_geometry(load_robot(PARAMS["robot"]))


def train(p: dict, points):
    """train_boter on the nominal geometry G with p's sections."""
    return train_boter(points, G, p["model"], p["loss"], p["train"], p["workspace"]["radius_quantile"], progress=False)


@pytest.fixture()
def points(tmp_path, monkeypatch):
    """120 poses whose measured positions carry a smooth 1 mm error."""
    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng(0)
    q = rng.uniform([-60, -120, 30, -150, 40, -90], [60, -40, 120, -30, 140, 90], (120, 6))
    theory = fk_numpy(q, load_robot(PARAMS["robot"]))
    err = np.stack([np.sin(np.radians(q[:, 1])), np.cos(np.radians(q[:, 2])), 0.5 * np.sin(np.radians(q[:, 0]))], 1)
    df = pd.DataFrame(q, columns=JOINTS_DEG)
    df[THEORY], df[MEAS], df[ERR] = theory, theory + err, err
    df["split"] = ["train"] * 96 + ["val"] * 12 + ["test"] * 12
    return df


def test_same_seed_same_model_and_best_checkpoint_kept(points):
    m1, h1 = train(PARAMS, points)
    m2, h2 = train(PARAMS, points)
    for (k, a), (_, b) in zip(m1.state_dict().items(), m2.state_dict().items()):
        assert torch.equal(a, b), k
    assert h1["best_val_mae_3d_mm"] == h2["best_val_mae_3d_mm"] and h1["best_epoch"] == h2["best_epoch"]
    # the returned weights are the best validation epoch's, not the last epoch's
    val = tensors(points[points.split == "val"])
    assert mae_3d(m1, *val) == pytest.approx(h1["best_val_mae_3d_mm"], rel=1e-12)
    start = np.linalg.norm(points.loc[points.split == "val", ERR].to_numpy(), axis=1).mean()
    assert h1["best_val_mae_3d_mm"] < start                      # it learned something


def test_early_stopping_and_a_different_seed_differs(points):
    p = json.loads(json.dumps(PARAMS))
    p["train"].update(max_epochs=200, patience=3, lr=3e-2)        # a rate that stops improving fast
    _, h = train(p, points)
    assert h["epochs_run"] < 200 and h["epochs_run"] - h["best_epoch"] == 3
    q = json.loads(json.dumps(PARAMS))
    q["model"]["init_seed"] = 4
    m1, _ = train(PARAMS, points)
    m2, _ = train(q, points)
    assert not torch.equal(m1.head.out.weight, m2.head.out.weight)


@pytest.mark.parametrize("change", [{"ema": 0.9}, {"members": 2}, {"ema": 0.9, "members": 2},
                                    {"lr_drop": 0.5, "lr_patience": 0, "max_epochs": 40}])
def test_ema_ensemble_and_lr_drop_training_are_deterministic_and_keep_their_best(points, change):
    p = json.loads(json.dumps(PARAMS))
    p["train"].update(change)
    m1, h1 = train(p, points)
    m2, h2 = train(p, points)
    for (k, a), (_, b) in zip(m1.state_dict().items(), m2.state_dict().items()):
        assert torch.equal(a, b), k
    val = tensors(points[points.split == "val"])
    assert mae_3d(m1, *val) == pytest.approx(h1["best_val_mae_3d_mm"], rel=1e-12)
    plain, _ = train(PARAMS, points)
    if "lr_drop" in change:                                   # the rate dropped, so the path differs
        assert h1["final_lr"] < p["train"]["lr"]
    if change.get("members", 1) == 1:                         # EMA weights are not the last step's
        assert not torch.equal(m1.head.out.weight, plain.head.out.weight)
    else:                                                     # member 1 is the plain model (seeds + 0)
        assert len(h1["members"]) == 2 and m1.n_members == 2
        if "ema" not in change:
            assert torch.equal(m1.stacked_m__head__out__weight[0], plain.head.out.weight)


def test_members_must_be_a_positive_integer(points):
    p = json.loads(json.dumps(PARAMS))
    p["train"]["members"] = 0
    with pytest.raises(ValueError, match=r"params.yaml train.members: a positive integer, got 0"):
        train(p, points)

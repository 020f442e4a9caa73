"""Training: same params and seed give the same model on CPU; the best validation checkpoint is kept;
`train.device`: the CPU path is the loop from before the setting, bit for bit; the CUDA graph's steps,
run eagerly on the CPU, give the same numbers; on a GPU (skipped without one) the model comes back on
the CPU."""
import copy
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from pipeline.lib.columns import ERR, JOINTS_DEG, MEAS, THEORY
from pipeline.lib.kinematics import fk_numpy, nominal_geometry
from pipeline.lib.robots import load_robot
from pipeline import train as train_stage
from pipeline.lib import config
from pipeline.lib.config import load_params
from pipeline.lib.loss import SPILoss, data_loss
from pipeline.lib.training import (EpochGraph, fit, load_model, make_model, mae_3d, resolve_device, save_model,
                                   tensors, train_boter)

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (torch sees none)")

PARAMS = {
    "robot": {"model": "ur5", "tool_mm": [0.0, 0.0, 0.0], "dh": None, "joint_limits_deg": None, "tcp": None},
    "model": {"d_model": 12, "n_layer": 1, "n_head": 2, "d_hidden": 16, "mask": "spi", "head": "resnet",
              "encoder": True, "physics": "nominal", "alpha0": 0.1, "dropout": 0.1, "fade_to": None, "init_seed": 3},
    "workspace": {"radius_quantile": 0.99, "coverage": 0.9},
    "loss": {"weighting": "uncertainty", "physics": True, "lambda_data": 1.0, "lambda_physics": 1.0},
    "train": {"lr": 1e-3, "weight_decay": 1e-6, "batch_size": 32, "grad_clip": 1.0, "max_epochs": 15,
              "patience": 5, "seed": 3, "ema": None, "members": 1,
              "lr_drop": None, "lr_patience": 40, "device": "cpu"},
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


# ----------------------------------------------------------------------------- train.device


def fit_before_train_device(model, loss_fn, train, val, cfg, live=None):
    """lib/training.py's fit as it was before `train.device` (commit 865b43e), kept to hold the CPU path
    to it bit for bit (its progress bar left out)."""
    q, p = train
    gen = torch.Generator().manual_seed(cfg["seed"])
    params = list(model.parameters()) + list(getattr(loss_fn, "parameters", lambda: [])())
    opt = torch.optim.AdamW(params, lr=cfg["lr"], weight_decay=cfg["weight_decay"])
    ema = (None if cfg["ema"] is None else torch.optim.swa_utils.AveragedModel(
        model, multi_avg_fn=torch.optim.swa_utils.get_ema_multi_avg_fn(cfg["ema"])))
    judged = model if ema is None else ema.module
    sched = (None if cfg["lr_drop"] is None else torch.optim.lr_scheduler.ReduceLROnPlateau(
        opt, factor=cfg["lr_drop"], patience=cfg["lr_patience"], threshold=0.0))
    best, best_epoch, best_state = np.inf, -1, None
    for epoch in range(cfg["max_epochs"]):
        model.train()
        losses = []
        for idx in torch.randperm(len(q), generator=gen).split(cfg["batch_size"]):
            p_pred, p_theory = model(q[idx])
            loss, parts = loss_fn(p_pred, p[idx], p_theory)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg["grad_clip"])
            opt.step()
            if ema is not None:
                ema.update_parameters(model)
            losses.append((loss.item(), parts, (p_pred - p[idx]).detach().norm(dim=1).sum().item()))
        val_mae = mae_3d(judged, *val)
        train_mae = sum(l[2] for l in losses) / len(q)
        if val_mae < best:
            best, best_epoch, best_state = val_mae, epoch, copy.deepcopy(judged.state_dict())
        if sched is not None:
            sched.step(val_mae)
        if live is not None:
            row = {"loss": float(np.mean([l[0] for l in losses])),
                   "data_loss": float(np.mean([l[1]["data"] for l in losses])),
                   "physics_loss": float(np.mean([l[1]["physics"] for l in losses])),
                   "train_mae_3d_mm": train_mae, "val_mae_3d_mm": val_mae, "lr": opt.param_groups[0]["lr"]}
            if hasattr(model, "alpha"):
                row["alpha"] = model.alpha.item()
            for name, value in row.items():
                live.log_metric(name, value, timestamp=False)
            live.next_step()
        if epoch - best_epoch >= cfg["patience"]:
            break
    model.load_state_dict(best_state)
    return {"epochs_run": epoch + 1, "best_epoch": best_epoch + 1, "best_val_mae_3d_mm": best,
            "final_lr": opt.param_groups[0]["lr"]}


class Rows:
    """A dvclive stand-in that keeps the logged rows."""

    def __init__(self):
        self.rows, self.row = [], {}

    def log_metric(self, name, value, timestamp=False):
        self.row[name] = value

    def next_step(self):
        self.rows.append(self.row)
        self.row = {}


# the settings the static epoch must carry: EMA (its first update a copy, then the lerp), a learning-rate
# drop, dropout (the data order and the dropout draws), the data term alone (a NaN physics term), the DNN
CASES = {"ema": ({"ema": 0.9}, {}, "boter"), "lr_drop": ({"lr_drop": 0.5, "lr_patience": 0, "max_epochs": 12}, {}, "boter"),
         "data_only_ema": ({"ema": 0.99, "batch_size": 40}, {"physics": False}, "boter"),
         "dnn": ({"ema": 0.9}, None, "dnn")}


def run_case(points, case, runner):
    """(model, history, logged rows) of one training run of CASES[case] by runner(model, loss, train, val, cfg, live)."""
    change, loss_change, kind = CASES[case]
    p = json.loads(json.dumps(PARAMS))
    p["train"].update(change, max_epochs=change.get("max_epochs", 8), patience=8)
    model = make_model(p["model"], G, kind)
    if kind == "boter":
        model.fade.fit(points.loc[points.split == "train", JOINTS_DEG].to_numpy(), 20.0)
        loss = SPILoss(**{**p["loss"], **loss_change})
    else:
        loss = lambda pp, pg, pt: (data_loss(pp, pg), {"data": 0.0, "physics": 0.0})   # train_dnn's
    live = Rows()
    train_t, val_t = tensors(points[points.split == "train"]), tensors(points[points.split == "val"])
    hist = runner(model, loss, train_t, val_t, p["train"], live)
    return model, hist, live.rows


def assert_same_run(a, b):
    (m1, h1, r1), (m2, h2, r2) = a, b
    s1, s2 = m1.state_dict(), m2.state_dict()
    assert list(s1) == list(s2)
    for k in s1:
        assert torch.equal(s1[k], s2[k]), k
    for k in ("epochs_run", "best_epoch", "best_val_mae_3d_mm", "final_lr"):
        assert h1[k] == h2[k], k
    assert json.dumps(r1) == json.dumps(r2)                      # every logged number (NaN included)


@pytest.mark.parametrize("case", ["ema", "lr_drop", "data_only_ema"])
def test_cpu_training_is_the_loop_from_before_train_device(points, case):
    """train.device cpu (auto without a GPU): the same weights, history and logged curves, bit for bit,
    as the loop before the setting existed, so dvc.lock's outputs stay as they are."""
    old = run_case(points, case, fit_before_train_device)
    new = run_case(points, case, lambda *a: fit(*a[:5], live=a[5], progress=False))
    assert_same_run(old, new)
    assert "device" not in new[1]                                # the CPU summary keeps its keys (and bytes)


@pytest.mark.parametrize("case", list(CASES))
def test_the_cuda_graphs_steps_run_eagerly_on_the_cpu_give_the_same_numbers(points, case):
    """EpochGraph (what CUDA captures: the shuffle as a gather from a static permutation, loss terms to a
    static table, the EMA as its lerp) run eagerly on the CPU: bit for bit the eager steps' numbers."""
    eager = run_case(points, case, lambda *a: fit(*a[:5], live=a[5], progress=False, graphed=False))
    graphed = run_case(points, case, lambda *a: fit(*a[:5], live=a[5], progress=False, graphed=True))
    assert_same_run(eager, graphed)


def test_train_device_setting(points, monkeypatch):
    assert "device" in config.SECTIONS["train"]
    assert load_params(Path(__file__).resolve().parents[1] / "params.yaml")["train"]["device"] == "auto"
    assert resolve_device("cpu") == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu")
    with pytest.raises(ValueError, match=r"train.device: 'cuda', but torch .* sees no CUDA GPU; use auto"):
        resolve_device("cuda")
    p = json.loads(json.dumps(PARAMS))
    p["train"]["device"] = "cuda:0"
    with pytest.raises(ValueError, match="sees no CUDA GPU"):                 # stops before any training
        train(p, points)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == torch.device("cuda")
    with pytest.raises(ValueError, match=r"train.device: unknown 'tpu'; use one of \('auto', 'cpu', 'cuda'\)"):
        resolve_device("tpu")


@CUDA
def test_cuda_training_comes_back_on_the_cpu_and_loads_anywhere(points, tmp_path):
    """On a GPU: trained there (the graph captured, recaptured after an lr drop), the model and its
    checkpoint hold CPU tensors, the checkpoint loads and predicts on the CPU, and it learned."""
    p = json.loads(json.dumps(PARAMS))
    p["train"].update(device="cuda", ema=0.9, lr_drop=0.5, lr_patience=0, max_epochs=12, patience=12)
    m, h = train(p, points)
    assert h["device"].startswith("cuda") and h["final_lr"] < p["train"]["lr"]
    assert all(t.device.type == "cpu" for t in list(m.state_dict().values()))
    save_model(m, tmp_path / "m.pt", p["model"])
    back = load_model(tmp_path / "m.pt")
    val = tensors(points[points.split == "val"])
    assert mae_3d(back, *val) == pytest.approx(h["best_val_mae_3d_mm"], rel=1e-6)
    start = np.linalg.norm(points.loc[points.split == "val", ERR].to_numpy(), axis=1).mean()
    assert h["best_val_mae_3d_mm"] < start


@CUDA
def test_cuda_graph_replays_the_eager_steps(points):
    """On a GPU: EpochGraph captures from its second epoch and replays; its weights follow the eager CUDA
    steps' (dropout off; AdamW's capturable form rounds differently, so close, not equal)."""
    p = json.loads(json.dumps(PARAMS))
    p["model"]["dropout"] = 0.0
    p["train"].update(device="cuda", ema=0.9, max_epochs=6, patience=6)
    train_t, val_t = tensors(points[points.split == "train"]), tensors(points[points.split == "val"])
    out = {}
    for graphed in (False, True):
        m = make_model(p["model"], G)
        fit(m, SPILoss(**p["loss"]), train_t, val_t, p["train"], progress=False, graphed=graphed)
        out[graphed] = m.state_dict()
    for k in out[False]:
        torch.testing.assert_close(out[True][k], out[False][k], rtol=1e-4, atol=1e-6)
    m = make_model(p["model"], G).cuda()
    opt = torch.optim.AdamW(m.parameters(), lr=1e-3, capturable=True)
    loss = SPILoss(**p["loss"]).cuda()
    steps = EpochGraph(m, loss, opt, None, train_t[0].cuda(), train_t[1].cuda(), 32, 1.0)
    for _ in range(3):
        rows = steps(torch.randperm(len(train_t[0])))
    assert steps.graph is not None and len(rows) == 3 and all(np.isfinite(r[0]) for r in rows)


def test_a_bad_setting_stops_train_before_it_resets_the_last_curves(trained_project, tmp_path, monkeypatch):
    """Issue 32 (minor): a failed direct run of the stage blanked reports/live/metrics.json and deleted
    its plots (dvclive resets its folder on start). The model's settings and device are checked first."""
    for f in ("models/calibration.json", "models/parts.json", "reports/frame.json", "data/interim/points.parquet",
              "data/interim/split.parquet"):
        (tmp_path / f).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / f).write_bytes((trained_project / f).read_bytes())
    live = tmp_path / "reports/live/metrics.json"
    live.parent.mkdir(parents=True)
    live.write_text('{"step": 254}\n')
    monkeypatch.chdir(tmp_path)
    p = load_params(trained_project / "params.yaml")
    p["model"].update(d_model=128, n_head=9)                     # 9 heads do not divide 128
    with pytest.raises(ValueError, match="n_head=9 does not divide d_model=128"):
        train_stage.run(p)
    assert live.read_text() == '{"step": 254}\n'

"""Training (sec. 3.2): BoTER with the SPI loss, and the paper's DNN baseline.

AdamW (lr 1e-4, weight decay 1e-6), batch 256, gradient clipping at 1.0, at
most `max_epochs`, the best checkpoint by validation 3D MAE kept, early stop
after `patience` epochs without improvement (the `train:` section). Beyond the paper:
    ema       validate and keep an exponential moving average of the weights
              (torch.optim.swa_utils.AveragedModel), not the last step's
    members   K models from seeds (init_seed + k, seed + k), averaged as one
              batched Ensemble (model.py): K times the training cost
    lr_drop   multiply the learning rate by this after `lr_patience` epochs without a better
              validation 3D MAE (ReduceLROnPlateau); null = constant (the paper)
"""
import copy
import time

import numpy as np
import pandas as pd
import torch
from tqdm import tqdm

from .columns import JOINTS_DEG, MEAS
from .errormaps import MAP_KEYS
from .kinematics import DTYPE, GEOMETRY_KEYS
from .loss import SPILoss, data_loss
from .model import DNN, BoTER, Ensemble, check_config, n_params
from .workspace import workspace_radius


def tensors(df: pd.DataFrame) -> tuple[torch.Tensor, torch.Tensor]:
    """Joint angles (n, 6) rad and measured positions (n, 3) mm as float64 tensors."""
    q = torch.tensor(np.radians(df[JOINTS_DEG].to_numpy()), dtype=DTYPE)
    return q, torch.tensor(df[MEAS].to_numpy(), dtype=DTYPE)


def make_model(cfg: dict, geometry: dict, kind: str = "boter"):
    """BoTER (the `model:` section) or the DNN baseline on `geometry`, weights from cfg["init_seed"]."""
    check_config(cfg)
    torch.manual_seed(cfg["init_seed"])
    if kind == "dnn":
        return DNN(geometry)
    return BoTER(geometry, d_model=cfg["d_model"], n_layer=cfg["n_layer"], n_head=cfg["n_head"],
                 d_hidden=cfg["d_hidden"], mask=cfg["mask"], head=cfg["head"], encoder=cfg["encoder"],
                 alpha0=cfg["alpha0"], dropout=cfg["dropout"], fade_to=cfg["fade_to"])


def save_model(model, path, cfg: dict) -> None:
    """A checkpoint that carries its own config: {"config": the `model:` section, "members": K,
    "state_dict"} (the physics branch's geometry and the training poses are buffers of the state)."""
    members = getattr(model, "n_members", 1)
    torch.save({"config": dict(cfg), "members": members, "state_dict": model.state_dict()}, path)


def load_model(path) -> BoTER | Ensemble:
    """The trained BoTER or Ensemble of a checkpoint (save_model; weights_only=True), in eval mode.
    Needs no params: the checkpoint says how to build it, its state holds the geometry."""
    ckpt = torch.load(path, weights_only=True)
    state = ckpt["state_dict"]
    geometry = {k: state[f"physics.{k}"] for k in GEOMETRY_KEYS + MAP_KEYS if f"physics.{k}" in state}
    members = [make_model(ckpt["config"], geometry) for _ in range(ckpt["members"])]
    model = members[0] if len(members) == 1 else Ensemble(members)
    model.load_state_dict(state)
    model.config = ckpt["config"]
    return model.eval()


@torch.no_grad()
def predict(model, df: pd.DataFrame, batch: int = 4096) -> np.ndarray:
    """Model predictions (n, 3) mm, base frame."""
    q, _ = tensors(df)
    return torch.cat([model(qb)[0] for qb in q.split(batch)]).numpy()


@torch.no_grad()
def mae_3d(model, q, p) -> float:
    model.eval()
    return float((model(q)[0] - p).norm(dim=1).mean())


def fit(model, loss_fn, train, val, cfg: dict, live=None, desc="train", progress=True) -> dict:
    """Train `model` on `train` = (q, p) with `loss_fn(p_pred, p_gt, p_theory) -> (loss, parts)`.

    Returns the history summary; `model` is left holding its best (validation) weights.
    """
    q, p = train
    gen = torch.Generator().manual_seed(cfg["seed"])
    params = list(model.parameters()) + list(getattr(loss_fn, "parameters", lambda: [])())
    opt = torch.optim.AdamW(params, lr=cfg["lr"], weight_decay=cfg["weight_decay"])
    ema = (None if cfg["ema"] is None else torch.optim.swa_utils.AveragedModel(
        model, multi_avg_fn=torch.optim.swa_utils.get_ema_multi_avg_fn(cfg["ema"])))
    judged = model if ema is None else ema.module           # the weights validated and kept
    sched = (None if cfg["lr_drop"] is None else torch.optim.lr_scheduler.ReduceLROnPlateau(
        opt, factor=cfg["lr_drop"], patience=cfg["lr_patience"], threshold=0.0))
    best, best_epoch, best_state, t0 = np.inf, -1, None, time.perf_counter()
    bar = tqdm(range(cfg["max_epochs"]), desc=desc, disable=not progress, mininterval=1.0)
    for epoch in bar:
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
        train_mae = sum(l[2] for l in losses) / len(q)       # over the epoch's batches, train mode
        if val_mae < best:
            best, best_epoch, best_state = val_mae, epoch, copy.deepcopy(judged.state_dict())
        if sched is not None:
            sched.step(val_mae)
        bar.set_postfix(val_mae=f"{val_mae:.4f}", best=f"{best:.4f}@{best_epoch}", refresh=False)
        if live is not None:
            row = {"loss": float(np.mean([l[0] for l in losses])),
                   "data_loss": float(np.mean([l[1]["data"] for l in losses])),
                   "physics_loss": float(np.mean([l[1]["physics"] for l in losses])),
                   "train_mae_3d_mm": train_mae, "val_mae_3d_mm": val_mae, "lr": opt.param_groups[0]["lr"]}
            if hasattr(model, "alpha"):
                row["alpha"] = model.alpha.item()
            for name, value in row.items():             # no wall-clock column: the TSVs are hashed (dvc.lock)
                live.log_metric(name, value, timestamp=False)
            live.next_step()
        if epoch - best_epoch >= cfg["patience"]:
            break
    model.load_state_dict(best_state)
    return {"epochs_run": epoch + 1, "best_epoch": best_epoch + 1, "best_val_mae_3d_mm": best,
            "final_lr": opt.param_groups[0]["lr"],
            "seconds": time.perf_counter() - t0,
            "seconds_per_epoch": (time.perf_counter() - t0) / (epoch + 1)}


def train_boter(df: pd.DataFrame, geometry: dict, model_cfg: dict, loss_cfg: dict, train_cfg: dict,
                radius_quantile: float, live=None, progress=True):
    """Build and train BoTER (or `train.members` of them, an Ensemble) with the SPI loss on df's
    train split, on the physics `geometry`, from the `model:`, `loss:` and `train:` sections and the
    workspace radius quantile; returns (model, summary)."""
    n_members = train_cfg["members"]
    if not (isinstance(n_members, int) and n_members >= 1):
        raise ValueError(f"params.yaml train.members: a positive integer, got {n_members!r}")
    train_q = df.loc[df.split == "train", JOINTS_DEG].to_numpy()
    radius = workspace_radius(train_q, radius_quantile)
    train, val = tensors(df[df.split == "train"]), tensors(df[df.split == "val"])
    members, runs = [], []
    for k in range(n_members):
        model = make_model({**model_cfg, "init_seed": model_cfg["init_seed"] + k}, geometry)
        model.fade.fit(train_q, radius)
        loss_fn = SPILoss(**loss_cfg)
        cfg = {**train_cfg, "seed": train_cfg["seed"] + k}
        desc = "SPI-BoTER" + (f" {k + 1}/{n_members}" if n_members > 1 else "")
        hist = fit(model, loss_fn, train, val, cfg, live if k == 0 else None, desc, progress)
        hist.update(alpha=model.alpha.item(), loss_weights=loss_fn.weights().tolist())
        members.append(model)
        runs.append(hist)
    model = members[0] if len(members) == 1 else Ensemble(members).eval()
    summary = dict(runs[0]) if len(runs) == 1 else {
        "members": runs, "best_val_mae_3d_mm": mae_3d(model, *val),
        **{k: sum(r[k] for r in runs) for k in ("seconds", "epochs_run")},
        "seconds_per_epoch": sum(r["seconds"] for r in runs) / sum(r["epochs_run"] for r in runs),
        "best_epoch": [r["best_epoch"] for r in runs], "alpha": [r["alpha"] for r in runs]}
    summary.update(n_params=n_params(members[0]) * len(members), n_train=len(train[0]), n_val=len(val[0]))
    return model, summary


def train_dnn(df: pd.DataFrame, geometry: dict, model_cfg: dict, train_cfg: dict, progress=True):
    """The paper's DNN baseline: same splits and optimiser, data loss only."""
    model = make_model(model_cfg, geometry, kind="dnn")
    loss_fn = lambda pp, pg, pt: (data_loss(pp, pg), {"data": 0.0, "physics": 0.0})
    train, val = tensors(df[df.split == "train"]), tensors(df[df.split == "val"])
    hist = fit(model, loss_fn, train, val, train_cfg, None, "DNN", progress)
    return model, hist

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
    device    auto (CUDA when torch sees a GPU, else the CPU), cpu or cuda: where `fit` trains. On
              the CPU the steps run eagerly, as they always have (bit for bit). On CUDA the model,
              every buffer (the float64 physics branch, the workspace's training poses) and the data
              move to the GPU once; each epoch's steps (forward, SPI loss, backward, clipping, AdamW,
              EMA) run as one captured CUDA graph (EpochGraph), so the small model's step is not
              bound by kernel launches; the trained model comes back on the CPU.
"""
import copy
import time

import numpy as np
import pandas as pd
import torch
from tqdm import tqdm

from pipeline.lib.learning.checkpoint import make_model
from pipeline.lib.learning.loss import SPILoss, data_loss
from pipeline.lib.learning.model import Ensemble, n_params, tensors
from pipeline.lib.learning.workspace import workspace_radius
from pipeline.lib.project.columns import JOINTS_DEG
from pipeline.lib.project.config import DEVICES         # declared with the settings' rules


def resolve_device(setting) -> torch.device:
    """`train.device`: auto (CUDA when torch sees a GPU, else the CPU), cpu, or cuda (cuda:N: that GPU).
    Asking for cuda where torch sees none stops with a message, before any training."""
    if setting == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if setting == "cpu":
        return torch.device("cpu")
    if isinstance(setting, str) and (setting == "cuda" or setting.startswith("cuda:")):
        if not torch.cuda.is_available():
            raise ValueError(f"params.yaml train.device: {setting!r}, but torch {torch.__version__} sees no "
                             "CUDA GPU; use auto (a GPU when there is one) or cpu")
        return torch.device(setting)
    raise ValueError(f"params.yaml train.device: unknown {setting!r}; use one of {DEVICES} (or cuda:N)")


@torch.no_grad()
def mae_3d(model, q, p) -> float:
    model.eval()
    return float((model(q)[0] - p).norm(dim=1).mean())


def eager_steps(model, loss_fn, opt, ema, q, p, perm, cfg) -> list:
    """One epoch's training steps, one after the other, over the batches of `perm`: per batch
    (loss, its terms, the batch's summed 3D error). The CPU's path."""
    losses = []
    for idx in perm.split(cfg["batch_size"]):
        p_pred, p_theory = model(q[idx])
        loss, parts = loss_fn(p_pred, p[idx], p_theory)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg["grad_clip"])
        opt.step()
        if ema is not None:
            ema.update_parameters(model)
        losses.append((loss.item(), parts, (p_pred - p[idx]).detach().norm(dim=1).sum().item()))
    return losses


def ema_step(ema, model) -> None:
    """AveragedModel.update_parameters after its first call (the first copies), without its host-side
    test of n_averaged, which a CUDA graph cannot hold: the same EMA function (a foreach lerp) per dtype."""
    groups = {}
    for avg, cur in zip(ema.parameters(), model.parameters()):
        a, c = groups.setdefault(avg.dtype, ([], []))
        a.append(avg.detach())
        c.append(cur.detach())
    for a, c in groups.values():
        ema.multi_avg_fn(a, c, ema.n_averaged)


class EpochGraph:
    """One epoch of training steps over data already on the device, written so that a CUDA graph can
    hold all of it: the shuffle is an index gather from a static permutation buffer, then per batch
    forward, loss, backward, clipping, AdamW and the EMA, each batch's loss terms written to a static
    table (read once an epoch, not per step).

    On CUDA the first epoch runs eagerly on a side stream (the warm-up: it makes AdamW's state and the
    EMA's first copy); the second is captured as one CUDA graph and every later epoch is one replay:
    one launch an epoch instead of thousands. AdamW's learning rate is a constant of the graph, so
    a drop (train.lr_drop) recaptures it. Elsewhere (the CPU) the same steps run eagerly, which is how
    a test checks this path's logic against eager_steps without a GPU: the same numbers, bit for bit.
    """

    def __init__(self, model, loss_fn, opt, ema, q, p, batch_size: int, grad_clip: float):
        self.model, self.opt, self.ema, self.q, self.p, self.grad_clip = model, opt, ema, q, p, grad_clip
        self.terms = getattr(loss_fn, "terms", loss_fn)        # SPILoss: its terms as tensors (no .item())
        n = len(q)
        self.perm = torch.zeros(n, dtype=torch.long, device=q.device)
        self.bounds = [(s, min(s + batch_size, n)) for s in range(0, n, batch_size)]
        self.stats = torch.zeros(len(self.bounds), 4, dtype=torch.float64, device=q.device)
        self.cuda = q.device.type == "cuda"
        self.graph, self.graph_lr, self.steps = None, None, 0

    def _run(self, first: bool) -> None:
        for j, (s, e) in enumerate(self.bounds):
            idx = self.perm[s:e]
            pb = self.p[idx]
            p_pred, p_theory = self.model(self.q[idx])
            loss, parts = self.terms(p_pred, pb, p_theory)
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.grad_clip)
            self.opt.step()
            if self.ema is not None:
                if first and j == 0:
                    self.ema.update_parameters(self.model)      # the first update copies the weights
                else:
                    ema_step(self.ema, self.model)
            row = (loss.detach(), parts["data"], parts["physics"], (p_pred - pb).detach().norm(dim=1).sum())
            for i, v in enumerate(row):
                if isinstance(v, torch.Tensor):
                    self.stats[j, i].copy_(v.detach())
                else:
                    self.stats[j, i].fill_(v)

    def __call__(self, perm: torch.Tensor) -> list:
        """The epoch's steps in the order `perm`; per batch (loss, its terms, the batch's summed 3D error)."""
        self.perm.copy_(perm)
        if self.cuda:
            with torch.cuda.device(self.q.device):
                self._cuda_epoch()
        else:
            self._run(first=self.steps == 0)
        self.steps += len(self.bounds)
        if self.ema is not None:
            self.ema.n_averaged.fill_(self.steps)
        return [(loss, {"data": d, "physics": ph}, err) for loss, d, ph, err in self.stats.tolist()]

    def _cuda_epoch(self) -> None:
        lr = self.opt.param_groups[0]["lr"]
        if self.steps == 0:                                      # warm-up, eagerly, on a side stream
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                self._run(first=True)
            torch.cuda.current_stream().wait_stream(side)
        else:
            if self.graph is None or lr != self.graph_lr:       # capture (again, after an lr drop)
                self.graph = None
                self.opt.zero_grad(set_to_none=True)            # gradients live in the graph's memory pool
                self.graph = torch.cuda.CUDAGraph()
                with torch.cuda.graph(self.graph):
                    self._run(first=False)
                self.graph_lr = lr
            self.graph.replay()                                  # capture records; the replay runs the epoch


def fit(model, loss_fn, train, val, cfg: dict, live=None, desc="train", progress=True, graphed=None) -> dict:
    """Train `model` on `train` = (q, p) with `loss_fn(p_pred, p_gt, p_theory) -> (loss, parts)`,
    on `cfg["device"]` (resolve_device).

    Returns the history summary; `model` is left holding its best (validation) weights, on the CPU.
    graphed: run each epoch through EpochGraph (True) or eager_steps (False); default: EpochGraph on
    CUDA (captured), eager_steps elsewhere. EpochGraph on the CPU runs its steps eagerly: the same
    numbers as eager_steps (a test holds it), so its logic is checked where there is no GPU.
    """
    device = resolve_device(cfg["device"])
    graphed = device.type == "cuda" if graphed is None else graphed
    if device.type != "cpu":        # the model with every buffer, the loss's weights and the data: once
        model.to(device)
        if isinstance(loss_fn, torch.nn.Module):
            loss_fn.to(device)
        train, val = tuple(t.to(device) for t in train), tuple(t.to(device) for t in val)
    q, p = train
    gen = torch.Generator().manual_seed(cfg["seed"])        # on the CPU: the same data order on any device
    params = list(model.parameters()) + list(getattr(loss_fn, "parameters", lambda: [])())
    opt = torch.optim.AdamW(params, lr=cfg["lr"], weight_decay=cfg["weight_decay"],
                            **({"capturable": True} if graphed and device.type == "cuda" else {}))
    ema = (None if cfg["ema"] is None else torch.optim.swa_utils.AveragedModel(
        model, multi_avg_fn=torch.optim.swa_utils.get_ema_multi_avg_fn(cfg["ema"])))
    judged = model if ema is None else ema.module           # the weights validated and kept
    sched = (None if cfg["lr_drop"] is None else torch.optim.lr_scheduler.ReduceLROnPlateau(
        opt, factor=cfg["lr_drop"], patience=cfg["lr_patience"], threshold=0.0))
    steps = EpochGraph(model, loss_fn, opt, ema, q, p, cfg["batch_size"], cfg["grad_clip"]) if graphed else None
    best, best_epoch, best_state, t0 = np.inf, -1, None, time.perf_counter()
    # early stopping ends most runs long before max_epochs: no time left to guess, the patience shown instead
    bar = tqdm(range(cfg["max_epochs"]), desc=desc, disable=not progress, mininterval=1.0, unit="epoch",
               bar_format="{desc}: epoch {n_fmt} (at most {total_fmt}), {elapsed}, {rate_fmt}{postfix}")
    for epoch in bar:
        model.train()
        perm = torch.randperm(len(q), generator=gen)
        losses = steps(perm) if graphed else eager_steps(model, loss_fn, opt, ema, q, p, perm, cfg)
        val_mae = mae_3d(judged, *val)
        train_mae = sum(l[2] for l in losses) / len(q)       # over the epoch's batches, train mode
        if val_mae < best:
            best, best_epoch, best_state = val_mae, epoch, copy.deepcopy(judged.state_dict())
        if sched is not None:
            sched.step(val_mae)
        bar.set_postfix(val_mae=f"{val_mae:.4f}", best=f"{best:.4f}@{best_epoch}",
                        stops_in=f"{cfg['patience'] - (epoch - best_epoch)} epochs without a better val",
                        refresh=False)
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
    if best_state is None:                    # never a finite validation error: nothing to keep
        raise ValueError(f"{desc}: training diverged: the validation 3D MAE was {val_mae} in each of its "
                         f"{epoch + 1} epoch(s), never finite; lower train.lr ({cfg['lr']}) or check the data")
    model.load_state_dict(best_state)
    if device.type != "cpu":                                 # predictions and the checkpoint: CPU tensors
        model.to("cpu")
        if isinstance(loss_fn, torch.nn.Module):
            loss_fn.to("cpu")
    out = {"epochs_run": epoch + 1, "best_epoch": best_epoch + 1, "best_val_mae_3d_mm": best,
           "final_lr": opt.param_groups[0]["lr"],
           "seconds": time.perf_counter() - t0,
           "seconds_per_epoch": (time.perf_counter() - t0) / (epoch + 1)}
    if device.type != "cpu":                     # said where it applies only: CPU summaries keep their bytes
        out["device"] = str(device)
    return out


def independent_seeds(seeds, members: int, where: str) -> None:
    """Runs at `seeds` train members seed, seed + 1, .., seed + members - 1 (train_boter): a ValueError naming
    `where` where two runs would share a member (their spread would then understate the seeds')."""
    taken = [s + k for s in seeds for k in range(members)]
    if len(set(taken)) < len(taken):
        raise ValueError(f"{where}: seeds {list(seeds)} with train.members = {members} share members (a run at seed s "
                         f"trains s .. s + {members - 1}): space the seeds at least {members} apart")


def train_boter(df: pd.DataFrame, geometry: dict, model_cfg: dict, loss_cfg: dict, train_cfg: dict,
                radius_quantile: float, live=None, progress=True):
    """Build and train BoTER (or `train.members` of them, an Ensemble) with the SPI loss on df's
    train split, on the physics `geometry`, from the `model:`, `loss:` and `train:` sections and the
    workspace radius quantile; returns (model, summary)."""
    n_members = train_cfg["members"]
    if not (isinstance(n_members, int) and n_members >= 1):
        raise ValueError(f"params.yaml train.members: a positive integer, got {n_members!r}")
    resolve_device(train_cfg["device"])                     # a device that cannot be had stops here
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
    """The paper's DNN baseline: same splits, optimiser and device, data loss only."""
    resolve_device(train_cfg["device"])
    model = make_model(model_cfg, geometry, kind="dnn")
    loss_fn = lambda pp, pg, pt: (data_loss(pp, pg), {"data": 0.0, "physics": 0.0})
    train, val = tensors(df[df.split == "train"]), tensors(df[df.split == "val"])
    hist = fit(model, loss_fn, train, val, train_cfg, None, "DNN", progress)
    return model, hist

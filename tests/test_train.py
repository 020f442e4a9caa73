"""Training: same params and seed give the same model on CPU; the best validation checkpoint is kept;
`train.device`: on the CPU a run repeats bit for bit, its curves are its model's, the data order is
train.seed's alone and the EMA is what is validated and kept; the CUDA graph's steps, run eagerly on
the CPU, give the same numbers; on a GPU (skipped without one) the model comes back on the CPU."""
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from pipeline.lib.learning.checkpoint import load_model, make_model, save_model
from pipeline.lib.learning.loss import SPILoss, data_loss
from pipeline.lib.learning.model import tensors
from pipeline.lib.learning.training import EpochGraph, fit, mae_3d, resolve_device, train_boter
from pipeline.lib.project import config
from pipeline.lib.project.columns import ERR, JOINTS_DEG, MEAS, THEORY
from pipeline.lib.project.config import load_params
from pipeline.lib.robot.kinematics import fk_numpy, nominal_geometry
from pipeline.lib.robot.robots import load_robot
from pipeline.stages import train as train_stage

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


def run_case(points, case, runner, **train):
    """(model, history, logged rows) of one training run of CASES[case] (8 epochs and no early stop unless
    `train`, further train: settings, says otherwise) by runner(model, loss, train, val, cfg, live)."""
    change, loss_change, kind = CASES[case]
    p = json.loads(json.dumps(PARAMS))
    p["train"].update(change, max_epochs=change.get("max_epochs", 8), patience=8)
    p["train"].update(train)
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


def cpu_fit(model, loss, train, val, cfg, live):
    """fit as train_boter calls it on the CPU (its default path: the eager steps)."""
    return fit(model, loss, train, val, cfg, live=live, progress=False)


ROW = ["loss", "data_loss", "physics_loss", "train_mae_3d_mm", "val_mae_3d_mm", "lr", "alpha"]   # a curve row
SUMMARY = {"epochs_run", "best_epoch", "best_val_mae_3d_mm", "final_lr", "seconds", "seconds_per_epoch"}


@pytest.mark.parametrize("case", ["ema", "lr_drop", "data_only_ema"])
def test_cpu_training_repeats_bit_for_bit_and_its_curves_are_its_model(points, case):
    """train.device cpu (auto without a GPU): a second run gives the same weights, history and logged
    curves, bit for bit, so dvc.lock's outputs stay as they are. One curve row an epoch; the weights kept
    (the EMA's) score exactly the lowest validation error of the curve, logged at best_epoch; the run stops
    `patience` epochs after it (lr 3e-2: ema after 23 epochs, its best the 20th; lr_drop after 6, its best
    the 3rd); the logged rate halves after each epoch without a new best (lr_drop); without the physics
    term its curve is NaN; the CPU summary keeps its keys (no device)."""
    early = {} if case == "data_only_ema" else {"lr": 3e-2, "patience": 3, "max_epochs": 40}
    model, h, rows = run = run_case(points, case, cpu_fit, **early)
    assert_same_run(run, run_case(points, case, cpu_fit, **early))
    assert set(h) == SUMMARY and len(rows) == h["epochs_run"] and all(list(r) == ROW for r in rows)
    val = [r["val_mae_3d_mm"] for r in rows]
    assert val.index(min(val)) == h["best_epoch"] - 1 and h["best_val_mae_3d_mm"] == min(val)
    assert mae_3d(model, *tensors(points[points.split == "val"])) == h["best_val_mae_3d_mm"]   # not the last epoch's
    if early:                                              # stopped early, past its best
        assert h["best_epoch"] < h["epochs_run"] < 40 and h["epochs_run"] - h["best_epoch"] == 3
    else:
        assert h["epochs_run"] == 8
    cfg = {**PARAMS["train"], **CASES[case][0], **early}
    not_best = np.cumsum([i > 0 and v >= min(val[:i]) for i, v in enumerate(val)])
    want = [cfg["lr"] * (cfg["lr_drop"] or 1.0) ** int(k) for k in not_best]
    assert [r["lr"] for r in rows] == want and h["final_lr"] == want[-1]
    assert h["final_lr"] == (3e-2 / 8 if case == "lr_drop" else cfg["lr"])      # lr_drop: 3 epochs not better
    assert all(np.isnan(r["physics_loss"]) == (case == "data_only_ema") for r in rows)


def test_the_ema_is_validated_and_kept_and_leaves_the_steps_alone(points):
    """train.ema: the training steps are the plain run's, bit for bit (every curve but the validation
    error: loss terms, train error, alpha, rate); the validation curve and the kept weights are the
    average's, at every epoch; an average of decay 0 is the last step's weights, so that run is the plain
    run, bit for bit (weights, history, curves)."""
    runs = {ema: run_case(points, "ema", cpu_fit, ema=ema) for ema in (None, 0.0, 0.9)}
    steps = lambda run: [{k: v for k, v in r.items() if k != "val_mae_3d_mm"} for r in run[2]]
    val = lambda run: [r["val_mae_3d_mm"] for r in run[2]]
    assert json.dumps(steps(runs[0.9])) == json.dumps(steps(runs[None])) and len(steps(runs[None])) == 8
    assert all(a != b for a, b in zip(val(runs[0.9]), val(runs[None])))
    assert not torch.equal(runs[0.9][0].head.out.weight, runs[None][0].head.out.weight)
    assert mae_3d(runs[0.9][0], *tensors(points[points.split == "val"])) == runs[0.9][1]["best_val_mae_3d_mm"]
    assert_same_run(runs[0.0], runs[None])


class SeenLoss(SPILoss):
    """The SPI loss, noting which training poses (row numbers, by their measured positions) each batch holds."""

    def __init__(self, p_train, **cfg):
        super().__init__(**cfg)
        self.rows = {tuple(r): i for i, r in enumerate(p_train.tolist())}
        self.batches = []

    def forward(self, p_pred, p_gt, p_theory):
        self.batches.append([self.rows[tuple(r)] for r in p_gt.tolist()])
        return super().forward(p_pred, p_gt, p_theory)


def test_each_epoch_visits_every_training_pose_once_in_an_order_of_train_seed_alone(points):
    """The data order: each epoch every one of the 96 training poses once, in batches of batch_size (40,
    40 and the 16 left), shuffled by a generator of its own seeded with train.seed: the initial weights
    and dropout's draws (init_seed, dropout) and the EMA do not move it; another train.seed does."""
    train_t, val_t = tensors(points[points.split == "train"]), tensors(points[points.split == "val"])

    def order(model_change={}, train_change={}):
        p = json.loads(json.dumps(PARAMS))
        p["model"].update(model_change)
        p["train"].update(train_change, batch_size=40, max_epochs=3, patience=3)
        loss = SeenLoss(train_t[1].numpy(), **p["loss"])
        fit(make_model(p["model"], G), loss, train_t, val_t, p["train"], progress=False)
        return loss.batches

    base = order()
    assert [len(b) for b in base] == [40, 40, 16] * 3
    for e in range(3):
        assert sorted(sum(base[3 * e:3 * e + 3], [])) == list(range(96))
    assert base[:3] != base[3:6]                                        # shuffled again each epoch
    assert order({"init_seed": 4, "dropout": 0.0}, {"ema": 0.9}) == base
    assert order(train_change={"seed": 4}) != base


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


def test_a_run_that_never_has_a_finite_validation_error_says_it_diverged(points):
    """Review D: an lr that blows the weights up (NaN from the first epoch) kept no best state and stopped
    with torch's `Expected state_dict to be dict-like, got NoneType`; now a ValueError says it diverged."""
    p = json.loads(json.dumps(PARAMS))
    p["train"].update(lr=1e6, max_epochs=2, patience=2)
    with pytest.raises(ValueError, match=r"training diverged: .*never finite; lower train.lr \(1000000.0\)"):
        train(p, points)


@pytest.mark.parametrize("damage", ["truncated", "junk", "empty", "not_a_checkpoint", "config_disagrees"])
def test_a_damaged_checkpoint_is_a_one_line_error_naming_its_file(points, tmp_path, damage):
    """Review D: a truncated or corrupt models/boter.pt stopped every command with torch's traceback
    (RuntimeError, KeyError: 101, EOFError), never naming the file; now a ValueError that names it
    (the commands' one_line prints it)."""
    model, _ = train(json.loads(json.dumps({**PARAMS, "train": {**PARAMS["train"], "max_epochs": 1}})), points)
    good = tmp_path / "good.pt"
    save_model(model, good, PARAMS["model"])
    bad = tmp_path / "boter.pt"
    if damage == "truncated":
        bad.write_bytes(good.read_bytes()[:5000])
    elif damage == "junk":
        bad.write_text("hello\n")
    elif damage == "empty":
        bad.write_bytes(b"")
    elif damage == "not_a_checkpoint":
        torch.save({"foo": 1}, bad)
    else:
        ckpt = torch.load(good, weights_only=True)
        ckpt["config"] = {**ckpt["config"], "d_model": 16}
        torch.save(ckpt, bad)
    with pytest.raises(ValueError, match=rf"^{bad}: "):
        load_model(bad)
    assert load_model(good).config == PARAMS["model"]

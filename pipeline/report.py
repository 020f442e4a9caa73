"""Stage report: figures, a reviewer's index page and a coloured point cloud.

    reports/plots/<name>.png   one PNG per entry of FIGURES (below)
    reports/index.md           settings, metrics beside the paper's, data / frame /
                               calibration / compensation summaries, the figures
    reports/points_error.ply   measured points (base frame, mm) coloured by |pred - meas|

Required inputs: data/interim/predictions.parquet and reports/metrics.json.
Every other input is optional; a figure or section whose input is missing is
skipped with a note in index.md (and in the log).

A figure is a function `fig_<name>(ctx) -> Figure | str`: a matplotlib Figure,
or a string saying why it was skipped. Its docstring's first line is its
caption in index.md. Adding a figure = writing the function + one FIGURES line.
"""
import math
from functools import cached_property
from pathlib import Path

import numpy as np
import pandas as pd

from .columns import AXES, JOINTS_DEG, MEAS, PRED, THEORY
from .config import (FRAME_JSON, MODEL_WEIGHTS, PARAMS, PREDICTIONS_TABLE, REPORTS, load_params,
                     logger, read_json)

log = logger(__name__)

PLOTS = REPORTS / "plots"
INDEX = REPORTS / "index.md"
PLY = REPORTS / "points_error.ply"
LIVE = REPORTS / "live" / "plots" / "metrics"
DPI = 110
SPLIT_COLORS = {"train": "tab:blue", "val": "tab:orange", "test": "tab:green"}
PLY_CMAP = "viridis"
PLY_PERCENTILE = 99.0                  # colour scale top: this percentile of |pred - meas|
DRIVE_TOL_MM = 0.5                     # the paper's acceptance band of the drive check
DISTANCE_BATCH = 64                    # test points in the distance-matrix figure

# The paper's numbers (UR5, 724 samples, test split; SPEC.md, Tables 5-9)
PAPER_TEST = {"x": {"mae": 0.1110, "mse": 0.0213, "rmse": 0.1461, "r2": 0.9682},
              "y": {"mae": 0.1537, "mse": 0.0379, "rmse": 0.1947, "r2": 0.8822},
              "z": {"mae": 0.1135, "mse": 0.0220, "rmse": 0.1484, "r2": 0.9612},
              "3d": {"mae": 0.2515, "mse": 0.0812, "rmse": 0.2850, "r2": 0.9479}}
PAPER_METHODS = {"DNN": {"mae": 0.3880, "rmse": 0.4386, "r2": 0.8787},
                 "GPSO-DNN": {"mae": 0.3405, "rmse": 0.3840, "r2": 0.9070},
                 "SPI-BoTER": {"mae": 0.2515, "rmse": 0.2850, "r2": 0.9479}}
PAPER_METHOD_OF = {"dnn": "DNN", "spi_boter_nominal": "SPI-BoTER"}   # our name -> paper row
PAPER_ABLATION = {"baseline": 0.2515, "data_only": 0.2880, "no_mask": 0.2756,
                  "body_mask": 0.2911, "no_resnet": 0.3128, "no_transformer": 0.3072}
PAPER_ABLATION_EPOCHS = {"baseline": 111, "no_mask": 402, "body_mask": 103, "no_resnet": 304,
                         "no_transformer": 341}
PAPER_DRIVE = {"x": {"std": 0.1355, "max": 0.4850, "min": 0.0010},      # Table 9, 50 points
               "y": {"std": 0.1438, "max": 0.7240, "min": 0.0260},
               "z": {"std": 0.1314, "max": 0.8220, "min": 0.0030}}
PAPER_DRIVE_WITHIN = "48/50 = 96 % (the text says 98 %)"
JOINT_LABELS = [f"J{i}" for i in range(1, 7)]


# ----------------------------------------------------------------------------- inputs

def optional_json(path: Path):
    return read_json(path) if path.exists() else None


def optional_csv(path: Path) -> pd.DataFrame | None:
    """The table at `path`, or None if it is missing or has no rows."""
    if not path.exists():
        return None
    df = pd.read_csv(path)
    return df if len(df) else None


class Context:
    """The run's inputs, read on first use."""

    def __init__(self, params: dict):
        self.params = params
        self.pred = pd.read_parquet(PREDICTIONS_TABLE)
        self.metrics = read_json(REPORTS / "metrics.json")
        missing = [c for c in ["point_id", "split"] + THEORY + MEAS + PRED if c not in self.pred]
        if missing:
            raise ValueError(f"{PREDICTIONS_TABLE}: missing column(s) {missing}")

    @cached_property
    def test(self) -> pd.DataFrame:
        """The test split (all points if the split has no test rows), in point-id order."""
        t = self.pred[self.pred.split == "test"]
        return (t if len(t) else self.pred).sort_values("point_id").reset_index(drop=True)

    @property
    def test_label(self) -> str:
        return "test set" if (self.pred.split == "test").any() else "all points (no test split)"

    @cached_property
    def residual(self) -> np.ndarray:
        """|pred - meas| per row of predictions.parquet, mm."""
        return np.linalg.norm(self.pred[PRED].to_numpy() - self.pred[MEAS].to_numpy(), axis=1)

    @cached_property
    def ply_scale(self) -> tuple[float, float]:
        """Colour scale (lo, hi) of the point cloud and of its preview figure, mm."""
        hi = float(np.percentile(self.residual, PLY_PERCENTILE)) if len(self.residual) else 1.0
        return 0.0, hi if hi > 0 else 1.0

    @cached_property
    def convergence(self):
        return optional_csv(REPORTS / "compensation_convergence.csv")

    @cached_property
    def drive(self):
        return optional_csv(REPORTS / "drive_check.csv")

    @cached_property
    def ablation(self):
        return optional_json(REPORTS / "ablation.json")

    def live(self, name: str) -> pd.DataFrame | None:
        """A dvclive curve: columns step, <name>."""
        path = LIVE / f"{name}.tsv"
        if not path.exists():
            return None
        df = pd.read_csv(path, sep="\t")
        return df if {"step", name} <= set(df.columns) and df[name].notna().any() else None


# ----------------------------------------------------------------------------- figures

def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _log_y(ax) -> None:
    """Log y axis with plain decimal tick labels (0.3, 1.5) rather than 3×10⁻¹."""
    from matplotlib.ticker import LogFormatter

    class Plain(LogFormatter):
        def _num_to_string(self, x, vmin, vmax):
            return f"{x:.3g}"

    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(Plain())
    ax.yaxis.set_minor_formatter(Plain(labelOnlyBase=False))


def _int_x(ax) -> None:
    from matplotlib.ticker import MaxNLocator
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))


def r2(real: np.ndarray, pred: np.ndarray) -> float:
    """R² of predicted against real errors, the denominator around the mean real error
    (metrics.regression_metrics' definition)."""
    ss = ((real - real.mean()) ** 2).sum()
    return float(1 - ((pred - real) ** 2).sum() / ss) if ss > 0 else math.nan


def fig_error_scatter(ctx: Context):
    """Predicted vs real position error per axis on the test set (the paper's "True vs.
    Predicted Error Scatter"): x = real Δ = meas − theory, y = predicted Δ̂ = pred − theory, mm."""
    plt = _plt()
    t = ctx.test
    real = t[MEAS].to_numpy() - t[THEORY].to_numpy()
    pred = t[PRED].to_numpy() - t[THEORY].to_numpy()
    fig, axs = plt.subplots(1, 3, figsize=(12, 4.3), constrained_layout=True)
    for k, (ax, a) in enumerate(zip(axs, AXES)):
        lo = min(real[:, k].min(), pred[:, k].min())
        hi = max(real[:, k].max(), pred[:, k].max())
        pad = 0.05 * (hi - lo or 1.0)
        lim = (lo - pad, hi + pad)
        ax.plot(lim, lim, "k--", lw=1, label="y = x (perfect prediction)")
        ax.scatter(real[:, k], pred[:, k], s=14, alpha=0.75, color=f"C{k}",
                   label=f"{len(t)} points, R² = {r2(real[:, k], pred[:, k]):.4f}")
        ax.set(xlim=lim, ylim=lim, aspect="equal", title=f"{a} axis",
               xlabel=f"real error Δ{a} = meas − theory (mm)",
               ylabel=f"predicted error Δ̂{a} = pred − theory (mm)")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
    fig.suptitle(f"Predicted vs real position error, {ctx.test_label}, base frame (mm)")
    return fig


def fig_error_hist(ctx: Context):
    """Distribution of the 3D position error on the test set, mm: the model |pred − meas|
    against nominal DH |theory − meas| (what the robot does uncompensated)."""
    plt = _plt()
    t = ctx.test
    e_model = np.linalg.norm(t[PRED].to_numpy() - t[MEAS].to_numpy(), axis=1)
    e_nom = np.linalg.norm(t[THEORY].to_numpy() - t[MEAS].to_numpy(), axis=1)
    bins = np.linspace(0, max(e_model.max(), e_nom.max()) * 1.02 or 1.0, 41)
    fig, ax = plt.subplots(figsize=(8, 4.5), constrained_layout=True)
    name = ctx.metrics.get("model", "SPI-BoTER")
    for e, label, c in ((e_nom, "nominal DH |theory − meas|", "tab:gray"),
                        (e_model, f"{name} |pred − meas|", "tab:blue")):
        ax.hist(e, bins=bins, alpha=0.6, color=c, edgecolor="white",
                label=f"{label}: mean {e.mean():.4f}, max {e.max():.4f} mm")
        ax.axvline(e.mean(), color=c, ls="--", lw=1.2)
    ax.set(xlabel="3D position error (mm)", ylabel="number of points",
           title=f"3D position error distribution, {ctx.test_label} ({len(t)} points), mm")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=9)
    return fig


def fig_distance_matrices(ctx: Context):
    """Normalised squared-distance matrices of a test batch, as in the SPI loss (eqs. 11-16):
    D_theory / max, D_pred / max and their difference (dimensionless)."""
    import torch
    from matplotlib.colors import TwoSlopeNorm
    from .loss import sq_distance_matrix
    plt = _plt()
    t = ctx.test.head(DISTANCE_BATCH)
    if len(t) < 2:
        return "fewer than 2 test points"
    Dt = sq_distance_matrix(torch.tensor(t[THEORY].to_numpy()))
    Dp = sq_distance_matrix(torch.tensor(t[PRED].to_numpy()))
    Dt_n, Dp_n = (Dt / Dt.max()).numpy(), (Dp / Dp.max()).numpy()
    diff = Dp_n - Dt_n
    fig, axs = plt.subplots(1, 3, figsize=(15, 4.8), constrained_layout=True)
    panels = [(Dt_n, f"D_theory / max (max = {Dt.max():.3g} mm²)", "viridis", None),
              (Dp_n, f"D_pred / max (max = {Dp.max():.3g} mm²)", "viridis", None),
              (diff, "difference D_pred/max − D_theory/max", "RdBu_r",
               TwoSlopeNorm(0.0, -(m := float(np.abs(diff).max()) or 1e-12), m))]
    for ax, (M, title, cmap, norm) in zip(axs, panels):
        im = ax.imshow(M, cmap=cmap, norm=norm, vmin=None if norm else 0.0,
                       vmax=None if norm else 1.0, interpolation="nearest")
        ax.set(title=title, xlabel="test sample j (batch index)", ylabel="test sample i (batch index)")
        cb = fig.colorbar(im, ax=ax, shrink=0.85)
        cb.set_label("normalised squared distance (dimensionless)" if norm is None
                     else "difference (dimensionless)")
        cb.formatter.set_powerlimits((-2, 2))
    fig.suptitle(f"Normalised squared-distance matrices of a batch of {len(t)} test points "
                 f"(point-id order); SPI physics loss = mean(difference²) = {np.mean(diff ** 2):.3g}")
    return fig


LIVE_PANELS = [  # (title, [(tsv name, legend)], y label, log y)
    ("3D MAE per epoch, mm", [("train_mae_3d_mm", "train (train mode, over the epoch)"),
                              ("val_mae_3d_mm", "validation")], "3D MAE (mm)", True),
    ("Total loss (eq. 18, loss.weighting)", [("loss", "loss")], "weighted loss", None),
    ("Data loss L_data (eq. 10), mm²", [("data_loss", "L_data")], "mean |pred − meas|² (mm²)", True),
    ("Physics loss L_physics (eq. 16)", [("physics_loss", "L_physics")],
     "MSE of normalised D (dimensionless)", True),
    ("Fusion weight α (eq. 9)", [("alpha", "α")], "α (dimensionless)", False),
]


def fig_training_curves(ctx: Context):
    """Training and validation curves per epoch from dvclive (reports/live): 3D MAE (mm, log y),
    the loss terms and the fusion weight α; the star marks the best validation epoch."""
    plt = _plt()
    panels = [(title, [(ctx.live(n), n, lab) for n, lab in curves], ylab, logy)
              for title, curves, ylab, logy in LIVE_PANELS]
    panels = [(t, [c for c in cs if c[0] is not None], yl, lg) for t, cs, yl, lg in panels]
    panels = [p for p in panels if p[1]]
    if not panels:
        return f"no dvclive curves under {LIVE}"
    ncol = min(3, len(panels))
    nrow = math.ceil(len(panels) / ncol)
    fig, axs = plt.subplots(nrow, ncol, figsize=(5 * ncol, 3.8 * nrow), constrained_layout=True,
                            squeeze=False)
    for ax, (title, curves, ylab, logy) in zip(axs.flat, panels):
        for df, name, label in curves:
            ax.plot(df["step"] + 1, df[name], lw=1.2, label=label)
            if name == "val_mae_3d_mm":
                i = df[name].idxmin()
                ax.plot(df["step"][i] + 1, df[name][i], "*", ms=12, color="tab:red",
                        label=f"best val {df[name][i]:.4f} mm @ epoch {df['step'][i] + 1}")
        vals = np.concatenate([df[name].dropna().to_numpy() for df, name, _ in curves])
        if (logy or logy is None) and (vals > 0).all():     # None: log unless it goes <= 0
            _log_y(ax)
        _int_x(ax)
        ax.set(title=title, xlabel="epoch", ylabel=ylab)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    for ax in list(axs.flat)[len(panels):]:
        ax.axis("off")
    fig.suptitle("Training curves (dvclive, one point per epoch)")
    return fig


def fig_attention_maps(ctx: Context):
    """Attention weights per layer (rows) and head (columns), mean over the test set: query
    joint (row) attends to key joint (column); softmax weights, dimensionless; grey = masked."""
    if not ctx.params["model"].get("encoder", True):
        return "model.encoder is false (the No-Transformer variant): no attention to show"
    if not MODEL_WEIGHTS.exists():
        return f"{MODEL_WEIGHTS} not found"
    import torch
    from .train import load_model
    plt = _plt()
    model = load_model(ctx.params)
    t = ctx.test
    q = torch.as_tensor(np.radians(t[JOINTS_DEG].to_numpy()))
    A = model.attention_maps(q).mean(1).numpy()            # (n_layer, n_head, 6, 6)
    L, H = A.shape[:2]
    mask = model.mask.numpy() if model.mask is not None else np.zeros((6, 6), bool)
    cmap = plt.get_cmap("magma").with_extremes(bad="lightgrey")
    vmax = float(np.ceil(A.max() * 10) / 10) or 1.0        # one scale for every map
    size = 2.2 if H * L <= 16 else 1.55
    fig, axs = plt.subplots(L, H, figsize=(max(size * H + 1.4, 7.5), size * L + 1.1), squeeze=False,
                            constrained_layout=True)
    annotate = L * H <= 8
    for i in range(L):
        for j in range(H):
            ax = axs[i, j]
            im = ax.imshow(np.ma.masked_array(A[i, j], mask), cmap=cmap, vmin=0, vmax=vmax)
            ax.set_xticks(range(6), JOINT_LABELS if i == L - 1 else [""] * 6, fontsize=7)
            ax.set_yticks(range(6), JOINT_LABELS if j == 0 else [""] * 6, fontsize=7)
            ax.set_title(f"layer {i + 1}, head {j + 1}", fontsize=8)
            if annotate:
                for r in range(6):
                    for c in range(6):
                        if not mask[r, c]:
                            ax.text(c, r, f"{A[i, j, r, c]:.2f}", ha="center", va="center",
                                    fontsize=6, color="white" if A[i, j, r, c] < 0.6 * vmax else "black")
            if i == L - 1:
                ax.set_xlabel("key joint", fontsize=8)
            if j == 0:
                ax.set_ylabel("query joint", fontsize=8)
    fig.colorbar(im, ax=axs, shrink=0.8, label="attention weight (dimensionless)")
    fig.suptitle(f"Attention weights per layer and head, mean over {len(t)} points ({ctx.test_label})\n"
                 f"rows = query joint, columns = key joint; mask = {ctx.params['model'].get('mask')} "
                 "(grey = masked); dimensionless")
    return fig


def fig_compensation_convergence(ctx: Context):
    """Inverse compensation: residual |pred − target| (mm, log y) per solver iteration, the max
    and mean over the points, with each solver's stopping tolerance."""
    plt = _plt()
    df = ctx.convergence
    if df is None:
        return "reports/compensation_convergence.csv not found (compensate stage not run)"
    cfg = ctx.params.get("compensate", {})
    tols = {"lm": (cfg.get("tol_mm"), "tol_mm"),
            "adam": (math.sqrt(3 * cfg["tol_mse"]) if cfg.get("tol_mse") else None,
                     "√(3·tol_mse)")}
    solvers = list(dict.fromkeys(df["solver"]))
    fig, axs = plt.subplots(1, len(solvers), figsize=(6 * len(solvers), 4.3), squeeze=False,
                            constrained_layout=True, sharey=True)
    floor = 1e-9
    for ax, s in zip(axs[0], solvers):
        d = df[df.solver == s]
        ax.plot(d["iteration"], d["max_residual_mm"].clip(lower=floor), "-", marker="." if len(d) < 40 else None,
                lw=1.4, label="max over points")
        ax.plot(d["iteration"], d["mean_residual_mm"].clip(lower=floor), "--",
                marker="." if len(d) < 40 else None, lw=1.4, label="mean over points")
        tol, what = tols.get(s, (None, ""))
        if tol:
            ax.axhline(tol, color="tab:red", ls=":", lw=1.5, label=f"stop: {what} = {tol:.3g} mm")
        _log_y(ax)
        _int_x(ax)
        n = len(d) - 1
        ax.set(title=f"{s}: {n} iteration{'s' * (n != 1)} (until every point stopped)", xlabel="iteration",
               ylabel="residual |pred − target| (mm)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    fig.suptitle("Inverse compensation convergence per solver (residual in mm, log scale)")
    return fig


def fig_sample_distribution(ctx: Context):
    """The sampled poses in space: theory (nominal DH) positions in the base frame, mm,
    coloured by split."""
    plt = _plt()
    fig = plt.figure(figsize=(7.5, 6.5), constrained_layout=True)
    ax = fig.add_subplot(projection="3d")
    P = ctx.pred
    for s, c in SPLIT_COLORS.items():
        d = P[P.split == s]
        if len(d):
            ax.scatter(d.theory_x, d.theory_y, d.theory_z, s=8 if s == "train" else 16, color=c,
                       alpha=0.55 if s == "train" else 0.95, label=f"{s} ({len(d)})",
                       depthshade=False)
    _equal_3d(ax, P[THEORY].to_numpy())
    _labels_3d(ax)
    ax.set(title=f"Sample distribution by split, {len(P)} poses\n"
                 "(nominal DH positions, robot base frame, mm)")
    ax.legend(loc="upper left")
    return fig


def fig_points_error(ctx: Context):
    """Preview and colour key of reports/points_error.ply: measured points (base frame, mm)
    coloured by their residual |pred − meas| (mm), all splits."""
    plt = _plt()
    lo, hi = ctx.ply_scale
    P = ctx.pred[MEAS].to_numpy()
    fig = plt.figure(figsize=(7.5, 6.5), constrained_layout=True)
    ax = fig.add_subplot(projection="3d")
    sc = ax.scatter(*P.T, c=ctx.residual, cmap=PLY_CMAP, vmin=lo, vmax=hi, s=10, depthshade=False)
    _equal_3d(ax, P)
    _labels_3d(ax)
    ax.set(title=f"Residual error |pred − meas| of {len(P)} measured points (base frame, mm)\n"
                 f"colour scale {lo:g}–{hi:.3f} mm ({PLY_PERCENTILE:g}th percentile), "
                 "as in points_error.ply")
    fig.colorbar(sc, ax=ax, shrink=0.6, pad=0.08, extend="max", label="|pred − meas| (mm)")
    return fig


def fig_drive_check(ctx: Context):
    """Twin drive check (the paper's "Position Error of ... Test Points"): achieved − target
    per point before (recorded angles) and after compensation, mm, with the ±0.5 mm band."""
    plt = _plt()
    d = ctx.drive
    if d is None:
        return "reports/drive_check.csv missing or empty (no twin drive check: real data, or compensate.twin off)"
    before = d[[f"before_{a}" for a in AXES]].to_numpy()
    after = d[[f"after_{a}" for a in AXES]].to_numpy()
    nb, na = np.linalg.norm(before, axis=1), np.linalg.norm(after, axis=1)
    idx = np.arange(1, len(d) + 1)
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(11, 7.5), constrained_layout=True)
    ok_b = (np.abs(before) <= DRIVE_TOL_MM).all(1).mean()
    ok_a = (np.abs(after) <= DRIVE_TOL_MM).all(1).mean()
    a1.plot(idx, nb, "o-", ms=4, lw=0.8, color="tab:gray",
            label=f"before (recorded angles): mean {nb.mean():.3f}, max {nb.max():.3f} mm")
    a1.plot(idx, na, "o-", ms=4, lw=0.8, color="tab:blue",
            label=f"after (compensated angles): mean {na.mean():.3f}, max {na.max():.3f} mm")
    a1.axhline(DRIVE_TOL_MM, color="tab:red", ls="--", lw=1.2, label=f"{DRIVE_TOL_MM} mm tolerance")
    a1.set(xlabel="point (order of reports/drive_check.csv)", ylabel="3D error |achieved − target| (mm)",
           title="3D position error per point, before and after compensation (mm)")
    a1.set_ylim(bottom=0)
    a1.grid(alpha=0.3)
    a1.legend(fontsize=8, loc="upper right")
    for k, a in enumerate(AXES):
        a2.plot(idx, after[:, k], "o-", ms=4, lw=0.8, color=f"C{k}",
                label=f"after, {a}: std {after[:, k].std():.3f}, max |e| {np.abs(after[:, k]).max():.3f} mm")
    for s in (-1, 1):
        a2.axhline(s * DRIVE_TOL_MM, color="tab:red", ls="--", lw=1.2,
                   label=f"±{DRIVE_TOL_MM} mm tolerance" if s > 0 else None)
    a2.axhline(0, color="k", lw=0.6)
    m = max(np.abs(after).max(), DRIVE_TOL_MM) * 1.15
    a2.set(ylim=(-m, m), xlabel="point (order of reports/drive_check.csv)",
           ylabel="achieved − target (mm)",
           title=f"After compensation, per axis (base frame, mm): within ±{DRIVE_TOL_MM} mm on every "
                 f"axis {100 * ok_a:.0f} % of points (before {100 * ok_b:.0f} %)")
    a2.grid(alpha=0.3)
    a2.legend(fontsize=8, ncol=2, loc="upper right")
    fig.suptitle(f"Twin drive check of the compensation, {len(d)} points")
    return fig


def _norm_group(name: str) -> str:
    return name.lower().replace("-", "_").replace(" ", "_")


def fig_ablation(ctx: Context):
    """Ablation: test 3D MAE per variant (mm), mean ± std over training seeds, every seed as a
    dot, the paper's value as a red diamond."""
    plt = _plt()
    ab = ctx.ablation
    if not ab or not ab.get("groups"):
        return "reports/ablation.json not found (no ablation run)"
    groups = ab["groups"]
    names = list(groups)
    x = np.arange(len(names))
    mean = np.array([groups[n].get("test_3d_mae_mean", np.nan) for n in names], float)
    std = np.array([groups[n].get("test_3d_mae_std", 0.0) or 0.0 for n in names], float)
    fig, ax = plt.subplots(figsize=(max(7, 1.3 * len(names) + 2), 4.8), constrained_layout=True)
    ax.bar(x, mean, yerr=std, capsize=5, color="tab:blue", alpha=0.6, label="this run: mean ± std over seeds")
    dots = False
    for i, n in enumerate(names):
        runs = groups[n].get("runs")
        if runs:
            jitter = np.linspace(-0.15, 0.15, len(runs)) if len(runs) > 1 else [0.0]
            ax.plot(i + np.asarray(jitter), runs, "o", color="k", ms=4,
                    label=None if dots else "individual seeds")
            dots = True
        ax.annotate(f"{mean[i]:.4f}", (i, mean[i] + std[i]), textcoords="offset points",
                    xytext=(0, 4), ha="center", fontsize=8)
    paper = [PAPER_ABLATION.get(_norm_group(n), np.nan) for n in names]
    if np.isfinite(paper).any():
        ax.plot(x, paper, "D", color="tab:red", ms=8, label="paper (UR5, one run)")
    ax.set_xticks(x, names, rotation=15)
    ax.set(ylabel="test 3D MAE (mm)", title="Ablation: test 3D MAE per variant (mm)")
    top = np.nanmax(np.concatenate([mean + std, paper, *[groups[n].get("runs") or [] for n in names]]))
    ax.set_ylim(0, 1.3 * top)
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=8, loc="upper left", ncol=3)
    return fig


def fig_methods(ctx: Context):
    """Comparison methods (reports/metrics.json "baselines"): test 3D MAE per method, mm,
    with the paper's value where it reports the same method."""
    plt = _plt()
    base = ctx.metrics.get("baselines") or {}
    rows = [(n, m["test"]["3d"]["mae"]) for n, m in base.items() if "test" in m]
    if not rows:
        return "no baselines with a test split in reports/metrics.json"
    rows.sort(key=lambda r: r[1], reverse=True)
    names, vals = zip(*rows)
    y = np.arange(len(rows))
    model = ctx.metrics.get("model")
    fig, ax = plt.subplots(figsize=(8, 0.55 * len(rows) + 1.8), constrained_layout=True)
    colors = ["tab:blue" if n == model else "tab:gray" for n in names]
    ax.barh(y, vals, color=colors, alpha=0.8)
    for i, v in enumerate(vals):
        ax.text(v, i, f" {v:.4f}", va="center", fontsize=8)
    paper = [PAPER_METHODS[PAPER_METHOD_OF[n]]["mae"] if n in PAPER_METHOD_OF else np.nan for n in names]
    if np.isfinite(paper).any():
        ax.plot(paper, y, "D", color="tab:red", ms=8, label="paper's value (UR5)")
        ax.legend(fontsize=8, loc="upper right")
    ax.set_yticks(y, names)
    ax.set_xlim(0, max(max(vals), np.nanmax(paper) if np.isfinite(paper).any() else 0) * 1.18)
    ax.set(xlabel="test 3D MAE (mm)", title="Test 3D MAE per method (mm); blue = this run's model")
    ax.grid(alpha=0.3, axis="x")
    return fig


def _labels_3d(ax) -> None:
    for axis, name in zip((ax.xaxis, ax.yaxis, ax.zaxis), AXES):
        axis.set_label_text(f"{name} (mm)")
        axis.labelpad = 12


def _equal_3d(ax, P: np.ndarray) -> None:
    """Equal scale on the three axes of a 3D plot."""
    lo, hi = P.min(0), P.max(0)
    ax.set_box_aspect(np.maximum(hi - lo, 1e-9 + 0.02 * (hi - lo).max()))


# name -> function; the PNG is reports/plots/<name>.png, the order is index.md's
FIGURES = {
    "error_scatter": fig_error_scatter,
    "error_hist": fig_error_hist,
    "distance_matrices": fig_distance_matrices,
    "training_curves": fig_training_curves,
    "attention_maps": fig_attention_maps,
    "compensation_convergence": fig_compensation_convergence,
    "sample_distribution": fig_sample_distribution,
    "points_error": fig_points_error,
    "drive_check": fig_drive_check,
    "ablation": fig_ablation,
    "methods": fig_methods,
}


def caption(fn) -> str:
    return " ".join((fn.__doc__ or "").split("\n\n")[0].split())


def render_figures(ctx: Context, only=None) -> dict:
    """Write every figure; returns {name: ("ok", path) | ("skipped", note)}."""
    plt = _plt()
    PLOTS.mkdir(parents=True, exist_ok=True)
    done = {}
    for name, fn in FIGURES.items():
        if only is not None and name not in only:
            continue
        path = PLOTS / f"{name}.png"
        out = fn(ctx)
        if isinstance(out, str):
            path.unlink(missing_ok=True)                   # no stale figure from an earlier run
            done[name] = ("skipped", out)
            log.info("figure %s skipped: %s", name, out)
            continue
        out.savefig(path, dpi=DPI)
        plt.close(out)
        done[name] = ("ok", path)
    return done


# ----------------------------------------------------------------------------- point cloud

def write_ply(ctx: Context, path: Path = PLY) -> dict:
    """Measured points (base frame, mm) coloured by |pred - meas| with PLY_CMAP on ctx.ply_scale."""
    import matplotlib
    import open3d as o3d
    lo, hi = ctx.ply_scale
    rgb = matplotlib.colormaps[PLY_CMAP](np.clip((ctx.residual - lo) / (hi - lo), 0, 1))[:, :3]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(ctx.pred[MEAS].to_numpy(float)))
    pc.colors = o3d.utility.Vector3dVector(rgb)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not o3d.io.write_point_cloud(str(path), pc):
        raise OSError(f"open3d could not write {path}")
    return {"n": len(pc.points), "lo": lo, "hi": hi}


# ----------------------------------------------------------------------------- index.md

def fmt(v, nd=4) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, (int, np.integer)):
        return str(v)
    if isinstance(v, (float, np.floating)):
        if not math.isfinite(v):
            return "–"
        return f"{v:.{nd}g}" if (v != 0 and (abs(v) < 1e-3 or abs(v) >= 1e5)) else f"{v:.{nd}f}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(fmt(x, nd) for x in v) + "]"
    return str(v)


def table(header: list, rows: list) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(fmt(c) if not isinstance(c, str) else c for c in r) + " |" for r in rows]
    return "\n".join(out) + "\n"


def link(path: Path, text: str | None = None) -> str:
    """A relative link from reports/index.md to `path` if it exists, else the bare name."""
    path = Path(path)
    try:
        rel = path.relative_to(REPORTS).as_posix()
    except ValueError:
        rel = Path("..", path).as_posix()
    return f"[{text or rel}]({rel})" if path.exists() else f"`{text or path.as_posix()}` (not found)"


def section_settings(params: dict) -> str:
    lines = ["## Settings", "", f"From {link(PARAMS)} (one line per section):", "", "```yaml"]
    for sec, v in params.items():
        if isinstance(v, dict):
            body = ", ".join(f"{k}: {_yaml_inline(x)}" for k, x in v.items())
            lines.append(f"{sec}: {{{body}}}")
        else:
            lines.append(f"{sec}: {_yaml_inline(v)}")
    return "\n".join(lines + ["```", ""])


def _yaml_inline(v) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_yaml_inline(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_yaml_inline(x) for x in v) + "]"
    return str(v)


def section_metrics(ctx: Context) -> str:
    m = ctx.metrics
    counts = ctx.pred.split.value_counts()
    name = m.get("model", "model")
    out = ["## Model metrics", "",
           f"`{name}` per split and axis ({link(REPORTS / 'metrics.json')}; eqs. 27-42). Errors are "
           "prediction − measurement in mm; R² compares the predicted error Δ̂ = pred − theory "
           "with the real one Δ = meas − theory. The paper's SPI-BoTER test numbers (UR5, 724 "
           "samples; Tables 6 and 8, the baseline rows) are beside this run's test rows.", ""]
    rows = []
    for split in ("train", "val", "test"):
        if split not in m:
            continue
        for ax in AXES + ["3d"]:
            s = m[split][ax]
            row = [split if ax == "x" else "", fmt(int(counts.get(split, 0))) if ax == "x" else "",
                   ax.upper() if ax != "3d" else "3D", s["mae"], s["mse"], s["rmse"], s["r2"]]
            p = PAPER_TEST[ax] if split == "test" else {}
            row += [p.get("mae"), p.get("mse"), p.get("rmse"), p.get("r2")]
            rows.append(row)
    out.append(table(["split", "n", "axis", "MAE mm", "MSE mm²", "RMSE mm", "R²",
                      "paper MAE", "paper MSE", "paper RMSE", "paper R²"], rows))
    if "test" in m:
        t = m["test"]["3d"]
        p = PAPER_TEST["3d"]
        out += ["", f"**Test 3D: MAE {t['mae']:.4f} mm (paper {p['mae']}), RMSE {t['rmse']:.4f} mm "
                f"(paper {p['rmse']}), R² {t['r2']:.4f} (paper {p['r2']}).**", ""]
    return "\n".join(out)


def section_baselines(ctx: Context) -> str:
    out = ["## Comparison methods (test split)", ""]
    md = REPORTS / "baselines.md"
    if md.exists():
        out += [f"From {link(md)}:", "", md.read_text().strip(), ""]
    elif ctx.metrics.get("baselines"):
        out += ["From reports/metrics.json \"baselines\":", ""]
        rows = [[n, s["test"]["3d"]["mae"], s["test"]["3d"]["rmse"], s["test"]["3d"]["r2"]]
                for n, s in ctx.metrics["baselines"].items() if "test" in s]
        out += [table(["method (test)", "3D MAE mm", "3D RMSE mm", "3D R²"], rows)]
    else:
        out += ["_No baselines (reports/baselines.md and metrics.json \"baselines\" missing)._", ""]
    out += ["The paper's numbers (UR5, test split, Table 4):", "",
            table(["paper method", "3D MAE mm", "3D RMSE mm", "3D R²"],
                  [[k, v["mae"], v["rmse"], v["r2"]] for k, v in PAPER_METHODS.items()]),
            "Here `nominal_dh` is the uncompensated robot (nominal DH after the frame fit); "
            "`dnn` corresponds to the paper's DNN, `spi_boter_nominal` to its SPI-BoTER.", ""]
    return "\n".join(out)


def section_data(ctx: Context) -> str:
    out = ["## Data: ingest, frame, theory, split", ""]
    ing = optional_json(REPORTS / "ingest.json")
    if ing:
        dropped = ing.get("dropped_counts") or {}
        out += [f"**Ingest** ({link(REPORTS / 'ingest.json')}): rows read "
                + ", ".join(f"{k} {v}" for k, v in (ing.get("n_read") or {}).items())
                + f"; points kept **{ing.get('n_kept')}**; dropped: "
                + (", ".join(f"{n} {r}" for r, n in dropped.items()) if dropped else "none") + ".", ""]
        if ing.get("dropped"):
            shown = ing["dropped"][:20]
            out.append(table(["point_id", "file", "row", "reason", "detail"],
                             [[str(d.get("point_id")), str(d.get("file")), str(d.get("row")),
                               str(d.get("reason")), str(d.get("detail", ""))] for d in shown]))
            if len(ing["dropped"]) > len(shown):
                out.append(f"… and {len(ing['dropped']) - len(shown)} more in ingest.json.\n")
    else:
        out += ["_reports/ingest.json not found._", ""]
    fr = optional_json(FRAME_JSON)
    if fr:
        outl = fr.get("outliers") or []
        res = fr.get("outlier_residual_mm") or {}
        out += [f"**Frame** ({link(FRAME_JSON)}, base → tracker, {fr.get('method', 'kabsch')}): "
                f"rms {fmt(fr.get('rms_mm'))} mm, mean {fmt(fr.get('mean_mm'))} mm, max "
                f"{fmt(fr.get('max_mm'))} mm over n_used = {fr.get('n_used')} points; "
                f"tool offset {fmt(fr.get('tool_mm'), 3)} mm (flange frame); "
                f"condition {fmt(fr.get('condition'))}; translation t = {fmt(fr.get('t'), 2)} mm; "
                f"{len(outl)} outlier(s)"
                + (": " + ", ".join(f"{p} ({fmt(res.get(p), 3)} mm)" if p in res else p
                                    for p in outl[:30]) if outl else "")
                + ("…" if len(outl) > 30 else "") + ".", ""]
    else:
        out += ["_reports/frame.json not found._", ""]
    th = optional_json(REPORTS / "theory.json")
    if th:
        e = th.get("nominal_error_mm") or {}
        out += [f"**Theory** ({link(REPORTS / 'theory.json')}): {th.get('n_points')} points, "
                f"{th.get('n_dropped', 0)} dropped as frame outliers; nominal DH error after the "
                f"frame fit: mean {fmt(e.get('mean'))}, rms {fmt(e.get('rms'))}, max "
                f"{fmt(e.get('max'))} mm.", ""]
    else:
        out += ["_reports/theory.json not found._", ""]
    sp = optional_json(REPORTS / "split.json")
    counts = sp.get("counts") if sp else ctx.pred.split.value_counts().to_dict()
    out += ["**Split**: " + ", ".join(f"{k} {v}" for k, v in counts.items())
            + (f" (seed {sp.get('seed')}, fractions {fmt(sp.get('fractions'), 2)})" if sp else "")
            + ".", ""]
    return "\n".join(out)


def section_calibration() -> str:
    out = ["## Classical kinematic calibration", ""]
    c = optional_json(REPORTS / "calibration.json")
    if not c:
        return "\n".join(out + ["_reports/calibration.json not found (calibrate stage not run)._", ""])
    fixed = c.get("fixed") or []
    fixed_txt = (", ".join(f"{k} ({v})" for k, v in fixed.items()) if isinstance(fixed, dict)
                 else ", ".join(map(str, fixed)))
    out += [f"{link(REPORTS / 'calibration.json')}: {len(c.get('identified', []))} of "
            f"{c.get('n_candidates')} parameters identified (rank {c.get('rank')}), condition number "
            f"{fmt(c.get('condition_number'))}, residual σ {fmt(c.get('residual_sigma_mm'))} mm, "
            f"loss {c.get('loss')} (scale {fmt(c.get('loss_scale_mm'))} mm), {c.get('nfev')} evaluations.",
            "", f"Identified: {', '.join(c.get('identified', [])) or 'none'}.", "",
            f"Fixed (unidentifiable or not selected): {fixed_txt or 'none'}.", ""]
    if c.get("splits"):
        rows = [[s, v.get("n"), v["nominal"]["mean_mm"], v["calibrated"]["mean_mm"],
                 v["nominal"]["rms_mm"], v["calibrated"]["rms_mm"], v["nominal"]["max_mm"],
                 v["calibrated"]["max_mm"]] for s, v in c["splits"].items()]
        out.append(table(["split", "n", "nominal mean mm", "calibrated mean mm", "nominal rms",
                          "calibrated rms", "nominal max", "calibrated max"], rows))
    est = c.get("estimates") or {}
    if est:
        big = sorted(est.items(), key=lambda kv: -abs(kv[1]["delta"] / (kv[1]["se"] or 1e-12)))[:12]
        out += ["Largest corrections by |Δ/σ| (of " + str(len(est)) + "):", "",
                table(["parameter", "Δ", "σ", "unit"], [[k, v["delta"], v["se"], v["unit"]] for k, v in big])]
    return "\n".join(out)


def section_training() -> str:
    tr = optional_json(REPORTS / "train.json")
    if not tr:
        return "## Training\n\n_reports/train.json not found._\n"
    return ("## Training\n\n"
            f"{link(REPORTS / 'train.json')}: {tr.get('n_params')} parameters, {tr.get('n_train')} "
            f"training / {tr.get('n_val')} validation points; best validation 3D MAE "
            f"{fmt(tr.get('best_val_mae_3d_mm'))} mm at epoch {tr.get('best_epoch')} of "
            f"{tr.get('epochs_run')} run ({fmt(tr.get('seconds'), 3)} s, "
            f"{fmt(tr.get('seconds_per_epoch'), 3)} s/epoch); fusion weight α = {fmt(tr.get('alpha'))}; "
            f"loss weights (data, physics) {fmt(tr.get('loss_weights'))}. "
            "The paper's best epoch: 111 of 150.\n")


def drive_rows(dc: dict) -> list:
    rows = []
    for ax in AXES:
        b, a, p = dc["before"][ax], dc["after"][ax], PAPER_DRIVE[ax]
        rows.append([ax.upper(), b["std"], b["max"], b["min"], a["std"], a["max"], a["min"],
                     p["std"], p["max"], p["min"]])
    b, a = dc["before"]["3d"], dc["after"]["3d"]
    rows.append(["3D", b["std"], b["max"], b["min"], a["std"], a["max"], a["min"], None, None, None])
    tol = dc["after"].get("tol_mm", DRIVE_TOL_MM)
    nb, na = dc["before"].get("n"), dc["after"].get("n")
    rows.append([f"within ±{tol:g} mm (every axis)",
                 f"{round(dc['before']['within_tol_share'] * nb)}/{nb}", "", "",
                 f"{round(dc['after']['within_tol_share'] * na)}/{na}", "", "",
                 PAPER_DRIVE_WITHIN, "", ""])
    return rows


def drive_summary(ctx: Context, comp: dict | None) -> dict | None:
    """The drive check's Table 9 statistics: from compensation.json, else from drive_check.csv."""
    if comp and comp.get("drive_check"):
        return comp["drive_check"]
    if ctx.drive is None:
        return None
    from .metrics import drive_table
    d = ctx.drive
    zero = np.zeros((len(d), 3))
    return {w: drive_table(d[[f"{w}_{a}" for a in AXES]].to_numpy(), zero, DRIVE_TOL_MM)
            for w in ("before", "after")}


def section_compensation(ctx: Context) -> str:
    out = ["## Inverse compensation", ""]
    comp = optional_json(REPORTS / "compensation.json")
    if comp:
        solvers = [s for s in ("adam", "lm") if s in comp]
        out += [f"{link(REPORTS / 'compensation.json')}: {comp.get('n_points')} points; the Δθ table "
                f"{link(REPORTS / 'compensation.csv')} comes from solver `{comp.get('solver')}`. "
                "The paper (Adam): 147 iterations on average to 0.01 mm.", ""]
        rows = [[s, f"{100 * comp[s]['converged_share']:.1f} %", comp[s]["iterations_mean"],
                 comp[s]["iterations_max"], comp[s]["residual_mm_mean"], comp[s]["residual_mm_max"],
                 comp[s].get("ms_per_point")] for s in solvers]
        out.append(table(["solver", "converged", "iterations mean", "iterations max",
                          "residual mean mm", "residual max mm", "ms / point"], rows))
        rt = comp.get("realtime")
        if rt:
            out += [f"Single poses through the controller path (`pipeline/realtime.py`, two model "
                    f"evaluations per call): {100 * rt['verified_share']:.0f} % verified by the second "
                    f"evaluation, {100 * rt['converged_share']:.0f} % converged, residual max "
                    f"{fmt(rt['true_residual_mm_max'])} mm measured; where not verified, "
                    f"{fmt(rt['predicted_residual_mm_max'])} mm predicted, "
                    f"{fmt(rt['unverified_true_residual_mm_max'])} mm measured.", ""]
    else:
        out += ["_reports/compensation.json not found (compensate stage not run)._", ""]
    dc = drive_summary(ctx, comp)
    if dc:
        nf = dc.get("noise_floor_mm")
        out += ["### Drive check (the paper's Table 9 layout)", "",
                f"The compensated angles driven on the digital twin and measured "
                f"({link(REPORTS / 'drive_check.csv')}); achieved − target in the base frame, mm: "
                "std of the signed error, max and min of its absolute value per axis. (The paper's text "
                "gives a max deviation of 0.62 mm, below its own table's Y and Z maxima.)"
                + (f" Twin measurement noise floor {fmt(nf)} mm." if nf is not None else ""), "",
                table(["axis", "before std", "before max", "before min", "after std", "after max",
                       "after min", "paper std", "paper max", "paper min"], drive_rows(dc))]
    else:
        out += ["_No drive check (reports/drive_check.csv missing or empty: real data, or "
                "compensate.twin off); the compensation is then only checked against the model._", ""]
    return "\n".join(out)


def section_ablation(ctx: Context) -> str:
    ab = ctx.ablation
    if not ab or not ab.get("groups"):
        return ("## Ablation\n\n_reports/ablation.json not found: no ablation run for this "
                "report._\n")
    rows = []
    for n, g in ab["groups"].items():
        ep = g.get("epochs_to_best") or []
        rows.append([n, str(len(g.get("seeds") or g.get("runs") or [])), g.get("test_3d_mae_mean"),
                     g.get("test_3d_mae_std"), f"{np.mean(ep):.1f}" if ep else "–",
                     PAPER_ABLATION.get(_norm_group(n)), PAPER_ABLATION_EPOCHS.get(_norm_group(n))])
    return ("## Ablation\n\n" + f"{link(REPORTS / 'ablation.json')}, test 3D MAE over training seeds:\n\n"
            + table(["group", "seeds", "mean mm", "std mm", "epochs to best (mean)", "paper mm",
                     "paper epochs"], rows))


def section_figures(figs: dict) -> str:
    out = ["## Figures", ""]
    for name, (status, what) in figs.items():
        fn = FIGURES[name]
        if status == "ok":
            out += [f"### `{name}`", "", caption(fn), "", f"![{name}](plots/{name}.png)", ""]
        else:
            out += [f"### `{name}`", "", caption(fn), "", f"_Skipped: {what}._", ""]
    return "\n".join(out)


def section_pointcloud(ply: dict) -> str:
    return ("## Point cloud\n\n"
            f"{link(PLY)}: the {ply['n']} measured points (all splits; base frame, mm) coloured by "
            f"their residual |pred − meas| with the `{PLY_CMAP}` colormap, linear from "
            f"{ply['lo']:g} mm (dark purple) to {ply['hi']:.4f} mm (yellow; the "
            f"{PLY_PERCENTILE:g}th percentile, larger residuals clipped to yellow). Open it in "
            "any 3D viewer (Open3D, MeshLab, CloudCompare); the `points_error` figure is its "
            "preview with the colour key.\n")


def write_index(ctx: Context, figs: dict, ply: dict) -> str:
    m = ctx.metrics
    head = ["# SPI-BoTER calibration report", "",
            "Generated by `python -m pipeline.report` (dvc stage `report`); open this page first.", ""]
    if "test" in m:
        t = m["test"]["3d"]
        nom = (m.get("baselines") or {}).get("nominal_dh", {}).get("test", {}).get("3d")
        head += [f"**Summary:** model `{m.get('model', '?')}`, test 3D MAE **{t['mae']:.4f} mm**, "
                 f"RMSE {t['rmse']:.4f} mm, R² {t['r2']:.4f} (paper: 0.2515 / 0.2850 / 0.9479)"
                 + (f"; uncompensated nominal DH on the same points: {nom['mae']:.4f} mm" if nom else "")
                 + ".", ""]
    skipped = [n for n, (s, _) in figs.items() if s != "ok"]
    head += ["Contents: settings · model metrics · comparison methods · data · calibration · "
             "training · compensation · ablation · point cloud · figures"
             + (f" (skipped: {', '.join(skipped)})" if skipped else ""), ""]
    parts = ["\n".join(head), section_settings(ctx.params), section_metrics(ctx),
             section_baselines(ctx), section_data(ctx), section_calibration(), section_training(),
             section_compensation(ctx), section_ablation(ctx), section_pointcloud(ply),
             section_figures(figs)]
    text = "\n".join(p.rstrip() + "\n" for p in parts)
    INDEX.parent.mkdir(parents=True, exist_ok=True)
    INDEX.write_text(text)
    return text


# ----------------------------------------------------------------------------- stage

def run(params: dict) -> dict:
    ctx = Context(params)
    figs = render_figures(ctx)
    ply = write_ply(ctx)
    write_index(ctx, figs, ply)
    made = [n for n, (s, _) in figs.items() if s == "ok"]
    log.info("wrote %d figures to %s (%d skipped), %s, %s (%d points, colour 0-%.3f mm)",
             len(made), PLOTS, len(figs) - len(made), INDEX, PLY, ply["n"], ply["hi"])
    return {"figures": {n: s for n, (s, _) in figs.items()}, "ply_points": ply["n"],
            "ply_scale_mm": [ply["lo"], ply["hi"]]}


def main():
    run(load_params())


if __name__ == "__main__":
    main()

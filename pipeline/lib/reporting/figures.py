"""The report's figures: `fig_<name>(ctx) -> Figure | str`, a matplotlib Figure or a
string saying why it was skipped. Its docstring's first paragraph is its caption.
Adding a figure = writing the function + one FIGURES line.

`ctx` is the report stage's Context (duck-typed): params, metrics, pred (the predictions
table), convergence, drive, validation (tables or None), live(name) (a dvclive curve or
None) and model (the trained model or None).
"""
import math
from pathlib import Path

import numpy as np
import torch

from pipeline.lib.learning.loss import sq_distance_matrix
from pipeline.lib.project.columns import AXES, JOINTS_DEG, MEAS, PRED, THEORY
from pipeline.lib.project.config import logger
from pipeline.lib.reporting.paper import PAPER_ABLATION, PAPER_METHOD_OF, PAPER_METHODS
from pipeline.lib.robot.errormaps import ARCSEC, angle_terms

log = logger(__name__)

DPI = 110
SPLIT_COLORS = {"train": "tab:blue", "val": "tab:orange", "test": "tab:green"}
PLY_CMAP = "viridis"
PLY_PERCENTILE = 99.0                  # colour scale top: this percentile of |pred - meas|
DRIVE_TOL_MM = 0.5                     # the paper's acceptance band of the drive check
DISTANCE_BATCH = 64                    # test points in the distance-matrix figure
JOINT_LABELS = [f"J{i}" for i in range(1, 7)]


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


def split_test(pred):
    """(the test split in point-id order, its label); all points if there is no test split."""
    t = pred[pred.split == "test"]
    label = "test set" if len(t) else "all points (no test split)"
    return (t if len(t) else pred).sort_values("point_id").reset_index(drop=True), label


def residual(pred) -> np.ndarray:
    """|pred - meas| per row of the predictions table, mm."""
    return np.linalg.norm(pred[PRED].to_numpy() - pred[MEAS].to_numpy(), axis=1)


def ply_scale(res: np.ndarray) -> tuple[float, float]:
    """Colour scale (lo, hi) of the point cloud and of its preview figure, mm."""
    hi = float(np.percentile(res, PLY_PERCENTILE)) if len(res) else 1.0
    return 0.0, hi if hi > 0 else 1.0


def r2(real: np.ndarray, pred: np.ndarray) -> float:
    """R² of predicted against real errors, the denominator around the mean real error
    (metrics.regression_metrics' definition)."""
    ss = ((real - real.mean()) ** 2).sum()
    return float(1 - ((pred - real) ** 2).sum() / ss) if ss > 0 else math.nan


def fig_error_scatter(ctx):
    """Predicted vs real position error per axis on the test set (the paper's "True vs.
    Predicted Error Scatter"): x = real Δ = meas − theory, y = predicted Δ̂ = pred − theory, mm."""
    plt = _plt()
    t, label = split_test(ctx.pred)
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
    fig.suptitle(f"Predicted vs real position error, {label}, base frame (mm)")
    return fig


def fig_error_hist(ctx):
    """Distribution of the 3D position error on the test set, mm: the model |pred − meas|
    against nominal DH |theory − meas| (what the robot does uncompensated)."""
    plt = _plt()
    t, label = split_test(ctx.pred)
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
           title=f"3D position error distribution, {label} ({len(t)} points), mm")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=9)
    return fig


def fig_distance_matrices(ctx):
    """Normalised squared-distance matrices of a test batch, as in the SPI loss (eqs. 11-16):
    D_theory / max, D_pred / max and their difference (dimensionless)."""
    from matplotlib.colors import TwoSlopeNorm
    plt = _plt()
    t = split_test(ctx.pred)[0].head(DISTANCE_BATCH)
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
    ("Data loss L_data (eq. 10), mm²", [("data_loss", "L_data")], "mean |pred − meas|² (mm²)", True),
    ("Physics loss L_physics (eq. 16)", [("physics_loss", "L_physics")],
     "MSE of normalised D (dimensionless)", True),
    ("Fusion weight α (eq. 9)", [("alpha", "α")], "α (dimensionless)", False),
]


def fig_training_curves(ctx):
    """Training and validation curves per epoch from dvclive (reports/live): 3D MAE (mm, log y),
    the loss terms and the fusion weight α; the star marks the best validation epoch."""
    plt = _plt()
    panels = [(title, [(ctx.live(n), n, lab) for n, lab in curves], ylab, logy)
              for title, curves, ylab, logy in LIVE_PANELS]
    panels = [(t, [c for c in cs if c[0] is not None], yl, lg) for t, cs, yl, lg in panels]
    panels = [p for p in panels if p[1]]
    if not panels:
        return "no dvclive curves under reports/live/plots/metrics (train stage not run)"
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


def fig_attention_maps(ctx):
    """Attention weights per layer (rows) and head (columns), mean over the test set: query
    joint (row) attends to key joint (column); softmax weights, dimensionless; grey = masked."""
    model = ctx.model
    if model is None:
        return "no trained model (models/boter.pt not found)"
    if not model.config["encoder"]:
        return "model.encoder is false (the No-Transformer variant): no attention to show"
    plt = _plt()
    t, label = split_test(ctx.pred)
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
    fig.suptitle(f"Attention weights per layer and head, mean over {len(t)} points ({label})\n"
                 f"rows = query joint, columns = key joint; mask = {model.config['mask']} "
                 "(grey = masked); dimensionless")
    return fig


def fig_compensation_convergence(ctx):
    """Inverse compensation: residual |pred − target| (mm, log y) per solver iteration, the max
    and mean over the points, with each solver's stopping tolerance."""
    plt = _plt()
    df = ctx.convergence
    if df is None:
        return "reports/compensation_convergence.csv not found (compensate stage not run)"
    cfg = ctx.params["compensate"]
    tols = {"lm": (cfg["tol_mm"], "tol_mm"), "adam": (math.sqrt(3 * cfg["tol_mse"]), "√(3·tol_mse)")}
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


def fig_sample_distribution(ctx):
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


def fig_points_error(ctx):
    """Preview and colour key of reports/points_error.ply: measured points (base frame, mm)
    coloured by their residual |pred − meas| (mm), all splits."""
    plt = _plt()
    res = residual(ctx.pred)
    lo, hi = ply_scale(res)
    P = ctx.pred[MEAS].to_numpy()
    fig = plt.figure(figsize=(7.5, 6.5), constrained_layout=True)
    ax = fig.add_subplot(projection="3d")
    sc = ax.scatter(*P.T, c=res, cmap=PLY_CMAP, vmin=lo, vmax=hi, s=10, depthshade=False)
    _equal_3d(ax, P)
    _labels_3d(ax)
    ax.set(title=f"Residual error |pred − meas| of {len(P)} measured points (base frame, mm)\n"
                 f"colour scale {lo:g}–{hi:.3f} mm ({PLY_PERCENTILE:g}th percentile), "
                 "as in points_error.ply")
    fig.colorbar(sc, ax=ax, shrink=0.6, pad=0.08, extend="max", label="|pred − meas| (mm)")
    return fig


def fig_drive_check(ctx):
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


def fig_ablation(summary: dict):
    """Ablation: test 3D MAE per variant (mm), mean ± std over training seeds, every seed as a
    dot, the paper's value as a red diamond."""
    plt = _plt()
    groups = summary["groups"]
    names = list(groups)
    x = np.arange(len(names))
    mean = np.array([groups[n]["test_3d_mae_mean"] for n in names], float)
    std = np.array([groups[n]["test_3d_mae_std"] or 0.0 for n in names], float)     # one seed: no spread, no bar
    fig, ax = plt.subplots(figsize=(max(7, 1.3 * len(names) + 2), 4.8), constrained_layout=True)
    ax.bar(x, mean, yerr=std, capsize=5, color="tab:blue", alpha=0.6, label="this run: mean ± std over seeds")
    for i, n in enumerate(names):
        runs = groups[n]["runs"]
        jitter = np.linspace(-0.15, 0.15, len(runs)) if len(runs) > 1 else [0.0]
        ax.plot(i + np.asarray(jitter), runs, "o", color="k", ms=4,
                label="individual seeds" if i == 0 else None)
        ax.annotate(f"{mean[i]:.4f}", (i, mean[i] + std[i]), textcoords="offset points",
                    xytext=(0, 4), ha="center", fontsize=8)
    paper = [PAPER_ABLATION.get(n, np.nan) for n in names]
    if np.isfinite(paper).any():
        ax.plot(x, paper, "D", color="tab:red", ms=8, label="paper (UR5, one run)")
    ax.set_xticks(x, names, rotation=15)
    ax.set(ylabel="test 3D MAE (mm)", title="Ablation: test 3D MAE per variant (mm)")
    if not names:                                   # every group's seeds failed: said, on the declared figure
        ax.text(0.5, 0.5, "no group finished a seed (reports/ablation.json: all_seeds_failed)", ha="center",
                transform=ax.transAxes)
        return fig
    top = np.nanmax(np.concatenate([mean + std, paper, *[groups[n]["runs"] for n in names]]))
    ax.set_ylim(0, 1.3 * top)
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=8, loc="upper left", ncol=3)
    return fig


def fig_methods(ctx):
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


def fig_error_maps(ctx):
    """Per-joint error maps (parts stage): each joint's angle error, in arcsec, as a function of its own
    angle (solid where training measured that joint, dashed where the map fades out and says nothing),
    the part of the correction that carries to poses the network never saw."""
    plt = _plt()
    g = ctx.model.physics.geometry() if ctx.model is not None else {}
    if "amap_coef" not in g or not g["amap_coef"].abs().sum():
        return "no per-joint angle maps (parts stage off, or they did not lower the validation error)"
    coef, cover = g["amap_coef"].double(), g["amap_cover"].double()
    joints = [j for j in range(6) if coef[j].abs().sum() > 0]
    a = torch.arange(-180.0, 180.0, 0.25, dtype=torch.float64)
    q = a[:, None].expand(len(a), 6)                                     # every joint at the same angle
    out = {}
    for c in (cover, torch.ones_like(cover)):                            # with its coverage, and without
        idx, w = angle_terms(q, coef, c)                                 # (B, 6, 4)
        out[c is cover] = (coef[torch.arange(6)[None, :, None], idx] * w).sum(-1) / ARCSEC   # (B, 6) arcsec
    ncol = min(3, len(joints))
    fig, axs = plt.subplots(math.ceil(len(joints) / ncol), ncol, figsize=(5 * ncol, 3.4 * math.ceil(len(joints) / ncol)),
                            squeeze=False, constrained_layout=True)
    for ax, j in zip(axs.flat, joints):
        covered = cover[j, a.floor().long() % 360].numpy() > 0
        ax.plot(a, np.where(covered, out[True][:, j], np.nan), color="tab:blue", lw=1.2, label="measured range")
        ax.plot(a, np.where(covered, np.nan, out[False][:, j]), color="tab:blue", lw=0.8, ls="--",
                label="not measured (faded out)")
        ax.axhline(0, color="k", lw=0.5)
        ax.set(title=f"J{j + 1}: angle error, rms {float(out[True][covered, j].pow(2).mean().sqrt()):.1f}″",
               xlabel=f"joint {j + 1} angle (deg)", ylabel="error (arcsec)", xlim=(-180, 180))
        ax.grid(alpha=0.3)
    axs.flat[0].legend(fontsize=8)
    for ax in list(axs.flat)[len(joints):]:
        ax.axis("off")
    fig.suptitle("Per-joint error maps: what the calibration does not hold, as each joint's own angle error")
    return fig


# name -> function; the PNG is <out_dir>/<name>.png, the order is index.md's (what a reader needs first).
# (fig_ablation is not here: `python -m pipeline.commands.ablation` draws it from its own summary.)
def fig_validation(ctx):
    """Independent campaigns (validate stage): each judged point's 3D error per method, and the
    error distribution per method, split by whether the pose lies in the trained workspace."""
    plt = _plt()
    v = ctx.validation
    if v is None or not len(v):
        return "no validation campaign judged (none in validate.campaigns, or each skipped: reports/validation.json)"
    v = v[~v.registered]
    names = list(dict.fromkeys(v.campaign))
    methods = ("nominal", "calibrated", "calibrated_parts", "model")
    fig, axes = plt.subplots(len(names), 2, figsize=(14, 4.2 * len(names)), squeeze=False,
                             constrained_layout=True)
    for (a1, a2), name in zip(axes, names):
        c = v[v.campaign == name].reset_index(drop=True)
        inside = c.in_workspace.to_numpy()
        for k, m in enumerate(methods):
            e = c[f"error_{m}_mm"].to_numpy()
            a1.scatter(np.flatnonzero(inside), e[inside], s=9, color=f"C{k}", label=f"{m}, in workspace")
            a1.scatter(np.flatnonzero(~inside), e[~inside], s=12, marker="x", color=f"C{k}",
                       label=f"{m}, outside")
        a1.plot(c.uncertainty_mm.to_numpy(), color="k", lw=0.8, label="model's uncertainty_mm")
        a1.set(yscale="log", xlabel="judged point (campaign order)", ylabel="3D error (mm)",
               title=f"{name}: error per point ({inside.mean():.0%} in the trained workspace)")
        a1.legend(fontsize=7, ncol=1, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        a1.grid(alpha=0.3)
        data, labels = [], []
        for m in methods:
            for w, sel in (("in", inside), ("out", ~inside)):
                if sel.any():
                    data.append(c.loc[sel, f"error_{m}_mm"].to_numpy())
                    labels.append(f"{m.replace('_', ' + ').replace('parts', 'maps')}\n{w}")
        a2.boxplot(data, whis=(5, 95), showfliers=False)
        a2.set_xticks(range(1, len(labels) + 1), labels, fontsize=8)
        a2.set(ylabel="3D error (mm)", title=f"{name}: distribution (box: quartiles, whiskers 5-95 %)")
        a2.grid(alpha=0.3)
    return fig


FIGURES = {
    "methods": fig_methods,
    "error_maps": fig_error_maps,
    "validation": fig_validation,
    "error_scatter": fig_error_scatter,
    "error_hist": fig_error_hist,
    "drive_check": fig_drive_check,
    "compensation_convergence": fig_compensation_convergence,
    "training_curves": fig_training_curves,
    "sample_distribution": fig_sample_distribution,
    "points_error": fig_points_error,
    "distance_matrices": fig_distance_matrices,
    "attention_maps": fig_attention_maps,
}


def caption(fn) -> str:
    return " ".join((fn.__doc__ or "").split("\n\n")[0].split())


def save(fig, path: Path) -> None:
    """Write fig as a PNG at DPI and close it. No `Software` text chunk (matplotlib's version): the PNGs
    are hashed in dvc.lock, and only their pixels should count."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI, metadata={"Software": None})
    _plt().close(fig)


def render_figures(ctx, out_dir: Path) -> dict:
    """Write every figure to out_dir/<name>.png; returns {name: ("ok", path) | ("skipped", note)}."""
    done = {}
    for name, fn in FIGURES.items():
        path = Path(out_dir) / f"{name}.png"
        out = fn(ctx)
        if isinstance(out, str):
            path.unlink(missing_ok=True)                   # no stale figure from an earlier run
            done[name] = ("skipped", out)
            log.info("figure %s skipped: %s", name, out)
        else:
            save(out, path)
            done[name] = ("ok", path)
    return done


def write_ply(ctx, path: Path) -> dict:
    """Measured points (base frame, mm) coloured by |pred - meas| with PLY_CMAP on ply_scale."""
    import matplotlib
    import open3d as o3d
    res = residual(ctx.pred)
    lo, hi = ply_scale(res)
    rgb = matplotlib.colormaps[PLY_CMAP](np.clip((res - lo) / (hi - lo), 0, 1))[:, :3]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(ctx.pred[MEAS].to_numpy(float)))
    pc.colors = o3d.utility.Vector3dVector(rgb)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not o3d.io.write_point_cloud(str(path), pc):
        raise OSError(f"open3d could not write {path}")
    return {"n": len(pc.points), "lo": lo, "hi": hi, "path": path}

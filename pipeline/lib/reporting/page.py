"""The report's page, reports/index.md, as markdown text: settings, metrics beside the
paper's, data / frame / calibration / training / compensation summaries, the figures.

Each section takes what the report stage read (a dict, or None for a missing input)
and returns markdown. Links are relative to REPORTS (lib/project/artifacts.py), index.md's
directory; the stage writes the file.
"""
import math
from pathlib import Path

import numpy as np

from pipeline.lib.learning.metrics import drive_table
from pipeline.lib.project.artifacts import (HERE, BASELINES_MD, CALIBRATION_JSON, COMPENSATION_CSV,
                                            COMPENSATION_JSON, DRIVE_CSV, FRAME_JSON, INGEST_JSON,
                                            METRICS_JSON, PARAMS_FILE, PARTS_REPORT, REPORTS, THEORY_JSON,
                                            TRAIN_JSON)
from pipeline.lib.project.columns import AXES
from pipeline.lib.reporting.figures import DRIVE_TOL_MM, FIGURES, PLY_CMAP, PLY_PERCENTILE, caption
from pipeline.lib.reporting.paper import (PAPER_ABLATION_EPOCHS, PAPER_DRIVE, PAPER_DRIVE_WITHIN,
                                          PAPER_METHODS, PAPER_TEST)


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


def rel(path: Path) -> str:
    """`path` (relative to the project root) as seen from REPORTS."""
    path = Path(path)
    try:
        return path.relative_to(REPORTS).as_posix()
    except ValueError:
        return Path("..", path).as_posix()


def link(path: Path, text: str | None = None, root: Path = HERE) -> str:
    """A relative link to `path` if it exists in the project at `root`, else the bare name."""
    path = Path(path)
    return f"[{text or rel(path)}]({rel(path)})" if (root / path).exists() else f"`{text or path.as_posix()}` (not found)"


def section_settings(params: dict, root: Path = HERE) -> str:
    lines = ["## Settings", "", f"From {link(PARAMS_FILE, root=root)} (one line per section):", "", "```yaml"]
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


def section_metrics(m: dict, counts: dict, root: Path = HERE) -> str:
    name = m.get("model", "model")
    out = ["## Model metrics", "",
           f"`{name}` per split and axis ({link(METRICS_JSON, root=root)}; eqs. 27-42). Errors are "
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
                f"(paper {p['rmse']}), R² {fmt(t['r2'])} (paper {p['r2']}).**", ""]
    return "\n".join(out)


def section_baselines(m: dict, md: str | None, root: Path = HERE) -> str:
    """md: reports/baselines.md's text, or None."""
    out = ["## Comparison methods (test split)", ""]
    if md is not None:
        out += [f"From {link(BASELINES_MD, root=root)}:", "", md.strip(), ""]
    elif m.get("baselines"):
        out += ["From reports/metrics.json \"baselines\":", ""]
        rows = [[n, s["test"]["3d"]["mae"], s["test"]["3d"]["rmse"], s["test"]["3d"]["r2"]]
                for n, s in m["baselines"].items() if "test" in s]
        out += [table(["method (test)", "3D MAE mm", "3D RMSE mm", "3D R²"], rows)]
    else:
        out += ["_No baselines (reports/baselines.md and metrics.json \"baselines\" missing)._", ""]
    out += ["The paper's numbers (UR5, test split, Table 4):", "",
            table(["paper method", "3D MAE mm", "3D RMSE mm", "3D R²"],
                  [[k, v["mae"], v["rmse"], v["r2"]] for k, v in PAPER_METHODS.items()]),
            "Here `nominal_dh` is the uncompensated robot (nominal DH after the frame fit); "
            "`dnn` corresponds to the paper's DNN, `spi_boter_nominal` to its SPI-BoTER.", ""]
    return "\n".join(out)


def section_data(ing: dict | None, fr: dict | None, th: dict | None, sp: dict | None,
                 counts: dict, root: Path = HERE) -> str:
    """The ingest, frame, theory and split summaries; counts: points per split (if no split.json)."""
    out = ["## Data: ingest, frame, theory, split", ""]
    if ing:
        dropped = ing.get("dropped_counts") or {}
        out += [f"**Ingest** ({link(INGEST_JSON, root=root)}): rows read "
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
    if fr:
        outl = fr.get("outliers") or []
        res = fr.get("outlier_residual_mm") or {}
        out += [f"**Frame** ({link(FRAME_JSON, root=root)}, base → tracker, {fr.get('method', 'kabsch')}): "
                f"rms {fmt(fr.get('rms_mm'))} mm, mean {fmt(fr.get('mean_mm'))} mm, max "
                f"{fmt(fr.get('max_mm'))} mm over n_used = {fr.get('n_used')} points; "
                f"tool offset {fmt(fr.get('tool_mm'), 3)} mm (flange frame); "
                f"condition {fmt(fr.get('condition'))}; translation t = {fmt(fr.get('t'), 2)} mm; "
                f"{len(outl)} outlier(s)"
                + (": " + ", ".join(f"{p} ({fmt(res.get(p), 3)} mm)" if p in res else p
                                    for p in outl[:30]) if outl else "")
                + ("…" if len(outl) > 30 else "") + ".", ""]
        if len(fr.get("stations") or {}) > 1:
            out += ["Tracker stations (one frame each, the tool shared; the first is the base frame "
                    "every later stage works in):", "",
                    table(["station", "campaigns", "n", "n_used", "rms mm", "t mm"],
                          [[s, ", ".join(f["campaigns"]), f["n"], f["n_used"], f["rms_mm"], fmt(f["t"], 2)]
                           for s, f in fr["stations"].items()])]
    else:
        out += ["_reports/frame.json not found._", ""]
    if th:
        e = th.get("nominal_error_mm") or {}
        out += [f"**Theory** ({link(THEORY_JSON, root=root)}): {th.get('n_points')} points, "
                f"{th.get('n_dropped', 0)} dropped as frame outliers; nominal DH error after the "
                f"frame fit: mean {fmt(e.get('mean'))}, rms {fmt(e.get('rms'))}, max "
                f"{fmt(e.get('max'))} mm.", ""]
    else:
        out += ["_reports/theory.json not found._", ""]
    counts = sp.get("counts") if sp else counts
    out += ["**Split**: " + ", ".join(f"{k} {v}" for k, v in counts.items())
            + (f" (seed {sp.get('seed')}, fractions {fmt(sp.get('fractions'), 2)})" if sp else "")
            + ".", ""]
    return "\n".join(out)


def section_parts(r: dict | None, root: Path = HERE) -> str:
    """reports/parts.json: the per-joint error maps, what they gained, what they moved."""
    out = ["## Per-joint error maps (parts stage)", ""]
    if not r:
        return "\n".join(out + ["_reports/parts.json not found (parts stage not run)._", ""])
    s = r["splits"]
    out += [f"{link(PARTS_REPORT, root=root)}: {r.get('n_coefficients')} coefficients, "
            + ("**on**" if r.get("enabled") else "**off** (they did not lower the validation error)")
            + ". Each joint's angle error as a function of its own angle, and of the gravity torque it "
              "carries, fitted on the calibration's residual with the calibration's parameters re-estimated "
              "beside them; the model's physics branch carries them.", "",
            table(["split", "n", "calibration mm", "calibration + maps mm"],
                  [[k, v["n"], v["calibrated"]["mean_mm"], v["calibrated_parts"]["mean_mm"]] for k, v in s.items()]),
            table(["part", "joint", "rms arcsec", "displacement rms mm", "re-learned share"],
                  [[b["part"], b["joint"], b["coef_rms_arcsec"], b["displacement_rms_mm"], b["relearned_share"]]
                   for b in r.get("blocks", [])]),
            "Re-learned share: how much of a part's displacement the calibration's own parameters could "
            "make (0: nothing a DH, tilt, tool, base or compliance parameter can do).", ""]
    moved = sorted(((k, v) for k, v in (r.get("calibration_corrections") or {}).items() if v.get("calibration_se")),
                   key=lambda kv: -abs(kv[1]["delta"] / kv[1]["calibration_se"]))[:8]
    if moved:
        out += ["The calibration's parameters, re-estimated with the maps (largest moves in the calibration's "
                "own standard errors; deg, mm):", "",
                table(["parameter", "change", "calibration σ", "in σ"],
                      [[k, v["delta"], v["calibration_se"], v["delta"] / v["calibration_se"]] for k, v in moved])]
    th = r.get("thermal")
    if th:
        out += [f"Thermal reference: {th['column']} {fmt(th['temperature_ref_c'])} °C over the training points "
                f"(span {fmt(th['span_k'])} K); links expand by {th['cte_per_k']:g}/K on a campaign measured "
                "at another temperature.", ""]
    return "\n".join(out)


def section_calibration(c: dict | None, root: Path = HERE) -> str:
    out = ["## Classical kinematic calibration", ""]
    if not c:
        return "\n".join(out + ["_reports/calibration.json not found (calibrate stage not run)._", ""])
    fixed = c.get("fixed") or []
    fixed_txt = (", ".join(f"{k} ({v})" for k, v in fixed.items()) if isinstance(fixed, dict)
                 else ", ".join(map(str, fixed)))
    out += [f"{link(CALIBRATION_JSON, root=root)}: {len(c.get('identified', []))} of "
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
    stations = c.get("stations") or {}
    if len(stations) > 1:
        by = c.get("fixed_because_of_stations") or {}
        out += ["Station frames identified jointly with the robot (correction of each station's frame "
                "relative to the first's; rx, ry, rz deg, tx, ty, tz mm). Robot parameters fixed only "
                "because the station frames are free: " + (", ".join(by) if by else "none") + ".", "",
                table(["station", "rx", "ry", "rz", "tx", "ty", "tz"],
                      [[s] + [np.degrees(v) for v in d[:3]] + list(d[3:]) for s, d in stations.items()])]
    if c.get("campaigns") and len(c["campaigns"]) > 1:
        out += ["Per campaign (test split, mean 3D error mm):", "",
                table(["campaign", "n", "nominal", "calibrated"],
                      [[k, v["test"]["n"], v["test"]["nominal"]["mean_mm"], v["test"]["calibrated"]["mean_mm"]]
                       for k, v in c["campaigns"].items() if "test" in v])]
    est = c.get("estimates") or {}
    if est:
        big = sorted(est.items(), key=lambda kv: -abs(kv[1]["delta"] / (kv[1]["se"] or 1e-12)))[:12]
        out += ["Largest corrections by |Δ/σ| (of " + str(len(est)) + "):", "",
                table(["parameter", "Δ", "σ", "unit"], [[k, v["delta"], v["se"], v["unit"]] for k, v in big])]
    return "\n".join(out)


def section_training(tr: dict | None, root: Path = HERE) -> str:
    if not tr:
        return "## Training\n\n_reports/train.json not found._\n"
    return ("## Training\n\n"
            f"{link(TRAIN_JSON, root=root)}: {tr.get('n_params')} parameters, {tr.get('n_train')} "
            f"training / {tr.get('n_val')} validation points; best validation 3D MAE "
            f"{fmt(tr.get('best_val_mae_3d_mm'))} mm at epoch {tr.get('best_epoch')} of "
            f"{tr.get('epochs_run')} run (wall-clock times: reports/timings/train.json, kept out of the "
            f"hashed outputs); fusion weight α = {fmt(tr.get('alpha'))}; "
            f"loss weights (data, physics) {fmt(tr.get('loss_weights'))}. "
            f"The paper's best epoch: {PAPER_ABLATION_EPOCHS['baseline']} of 150.\n")


def drive_rows(dc: dict) -> list:
    rows = []
    for ax in AXES:
        b, a, p = dc["before"][ax], dc["after"][ax], PAPER_DRIVE[ax]
        rows.append([ax.upper(), b["std"], b["max"], b["min"], a["std"], a["max"], a["min"],
                     p["std"], p["max"], p["min"]])
    b, a = dc["before"]["3d"], dc["after"]["3d"]
    rows.append(["3D", b["std"], b["max"], b["min"], a["std"], a["max"], a["min"], None, None, None])
    tol = dc["after"]["tol_mm"]
    nb, na = dc["before"].get("n"), dc["after"].get("n")
    rows.append([f"within ±{tol:g} mm (every axis)",
                 f"{round(dc['before']['within_tol_share'] * nb)}/{nb}", "", "",
                 f"{round(dc['after']['within_tol_share'] * na)}/{na}", "", "",
                 PAPER_DRIVE_WITHIN, "", ""])
    return rows


def drive_summary(comp: dict | None, d) -> dict | None:
    """The drive check's Table 9 statistics: from compensation.json, else from the
    drive_check.csv table `d` (or None)."""
    if comp and comp.get("drive_check"):
        return comp["drive_check"]
    if d is None:
        return None
    zero = np.zeros((len(d), 3))
    return {w: drive_table(d[[f"{w}_{a}" for a in AXES]].to_numpy(), zero, DRIVE_TOL_MM)
            for w in ("before", "after")}


def section_compensation(comp: dict | None, drive, root: Path = HERE) -> str:
    """comp: compensation.json; drive: the drive_check.csv table (or None)."""
    out = ["## Inverse compensation", ""]
    if comp:
        solvers = [s for s in ("adam", "lm") if s in comp]
        out += [f"{link(COMPENSATION_JSON, root=root)}: {comp.get('n_points')} points; the Δθ table "
                f"{link(COMPENSATION_CSV, root=root)} comes from solver `{comp.get('solver')}`. "
                "The paper (Adam): 147 iterations on average to 0.01 mm.", ""]
        rows = [[s, f"{100 * comp[s]['converged_share']:.1f} %", comp[s]["iterations_mean"],
                 comp[s]["iterations_max"], comp[s]["residual_mm_mean"], comp[s]["residual_mm_max"]]
                for s in solvers]
        out.append(table(["solver", "converged", "iterations mean", "iterations max",
                          "residual mean mm", "residual max mm"], rows))
        rt = comp.get("realtime")
        if rt:
            out += [f"Single poses through the controller path (`pipeline/lib/runtime/realtime.py`, two model "
                    f"evaluations per call): {100 * rt['verified_share']:.0f} % verified by the second "
                    f"evaluation, {100 * rt['converged_share']:.0f} % converged, residual max "
                    f"{fmt(rt['true_residual_mm_max'])} mm measured; where not verified, "
                    f"{fmt(rt['predicted_residual_mm_max'])} mm predicted, "
                    f"{fmt(rt['unverified_true_residual_mm_max'])} mm measured.", ""]
    else:
        out += ["_reports/compensation.json not found (compensate stage not run)._", ""]
    dc = drive_summary(comp, drive)
    if dc:
        nf = dc.get("noise_floor_mm")
        out += ["### Drive check (the paper's Table 9 layout)", "",
                f"The compensated angles driven on the digital twin and measured "
                f"({link(DRIVE_CSV, root=root)}); achieved − target in the base frame, mm: "
                "std of the signed error, max and min of its absolute value per axis. (The paper's text "
                "gives a max deviation of 0.62 mm, below its own table's Y and Z maxima.)"
                + (f" Twin measurement noise floor {fmt(nf)} mm." if nf is not None else ""), "",
                table(["axis", "before std", "before max", "before min", "after std", "after max",
                       "after min", "paper std", "paper max", "paper min"], drive_rows(dc))]
    else:
        why = (comp or {}).get("drive_check_skipped") or ("reports/drive_check.csv missing or empty: real data, "
                                                          "or compensate.drive_check off")
        out += [f"_No drive check ({why}); the compensation is then only checked against the model._", ""]
    return "\n".join(out)


def section_ablation() -> str:
    """Static: the ablation is opt-in, and this page does not read its outputs."""
    md, js, png = (rel(REPORTS / f"ablation.{x}") for x in ("md", "json", "png"))
    return ("## Ablation\n\n"
            "Opt-in, outside `dvc repro`: `python -m pipeline.commands.ablation` (`--engine ray` in parallel) retrains each variant "
            "over `ablation.seeds` and writes "
            f"[{md}]({md}) (test 3D MAE per variant beside the paper's MAE and epochs), "
            f"[{js}]({js}) and the figure [{png}]({png}). This page does not read them.\n")


def section_figures(figs: dict) -> str:
    out = ["## Figures", ""]
    for name, (status, what) in figs.items():
        fn = FIGURES[name]
        if status == "ok":
            out += [f"### `{name}`", "", caption(fn), "", f"![{name}]({rel(what)})", ""]
        else:
            out += [f"### `{name}`", "", caption(fn), "", f"_Skipped: {what}._", ""]
    return "\n".join(out)


def section_pointcloud(ply: dict, root: Path = HERE) -> str:
    return ("## Point cloud\n\n"
            f"{link(ply['path'], root=root)}: the {ply['n']} measured points (all splits; base frame, mm) coloured by "
            f"their residual |pred − meas| with the `{PLY_CMAP}` colormap, linear from "
            f"{ply['lo']:g} mm (dark purple) to {ply['hi']:.4f} mm (yellow; the "
            f"{PLY_PERCENTILE:g}th percentile, larger residuals clipped to yellow). Open it in "
            "any 3D viewer (Open3D, MeshLab, CloudCompare); the `points_error` figure is its "
            "preview with the colour key.\n")


def section_validation(v: dict | None, uncertainty: dict | None) -> str:
    """Independent campaigns (validate stage), and how often the model's uncertainty held."""
    out = ["## Validation on independent campaigns", ""]
    if uncertainty:
        rows = [[s, u["in_workspace_share"], u["coverage"], u["uncertainty_mm_mean"]]
                for s, u in uncertainty.items() if isinstance(u, dict)]
        out += [f"The model's `uncertainty_mm` is meant to cover its 3D error on "
                f"{uncertainty['target_coverage']:.0%} of the poses inside the trained workspace; measured "
                "on the campaign it trained on:", "",
                table(["split", "in workspace", "error ≤ uncertainty", "mean uncertainty mm"], rows), ""]
        short = [r[0] for r in rows if r[2] < uncertainty["target_coverage"] - 0.02]
        if short:
            out += [f"**On the {', '.join(short)} split(s) the uncertainty covers fewer poses than the "
                    f"{uncertainty['target_coverage']:.0%} it targets: there it is optimistic** (it is fitted on the "
                    "validation split's errors; few poses make its quantile coarse).", ""]
    campaigns = (v or {}).get("campaigns") or {}
    out += [f"_`{n}` not judged: {why}._\n" for n, why in ((v or {}).get("skipped") or {}).items()]
    if not campaigns:
        return "\n".join(out + ["_No validation campaign judged._", ""])
    for name, c in campaigns.items():
        frame = ("the training campaign's frame (tracker not moved)" if c["frame"] == "same" else
                 f"each method's own rigid frame fitted on {c['n_register']} registration points")
        share = c["in_workspace_share"]
        out += [f"### `{name}`", "", f"{c['n']} points, {c['n_judged']} judged in {frame}. "
                f"**{share:.0%} of them lie inside the joint-space coverage the model was trained on"
                + ("; outside it the model extrapolates, and its numbers there are a guess to be "
                   "checked, not a calibration to trust.**" if share < 0.95 else ".**"), ""]
        rows = []
        for w, label in (("all", "all judged"), ("in", "in workspace"), ("out", "outside")):
            for m in ("nominal", "calibrated", "model"):
                st = ({"n": c["n_judged"], "mean": c["mean_3d_mm"][m], "p95": c["p95_3d_mm"][m],
                       "max": c["max_3d_mm"][m]} if w == "all" else c["by_workspace"][w][m])
                rows.append([label if m == "nominal" else "", m, st["n"], st["mean"], st["p95"], st["max"]])
        out += [table(["points", "method", "n", "mean mm", "p95 mm", "max mm"], rows), ""]
        cov = c["uncertainty_coverage"]
        cov0 = c.get("uncertainty_coverage_training")      # validate's since 2026-12-06
        alone = ("" if cov0 is None else f"; the training uncertainty alone, without the registration's residual: "
                 f"{fmt(cov0['all'], 2)}, inside {fmt(cov0['in'], 2)}, outside {fmt(cov0['out'], 2)}")
        out += [f"Model error ≤ its uncertainty_mm on {fmt(cov['all'], 2)} of the judged points "
                f"(inside {fmt(cov['in'], 2)}, outside {fmt(cov['out'], 2)}{alone}); mean uncertainty "
                f"{fmt(c['uncertainty_mm_mean'])} mm. Ingest kept {c['ingest']['n_kept']} points, dropped "
                f"{len(c['ingest']['dropped'])} ({c['ingest']['dropped_counts'] or 'none'}).", ""]
        if c.get("position_accuracy"):
            rows = [[m, a["positions"], a["ap_measured_mm"], a["ap_predicted_mm"], a["bar_error_mm"],
                     a.get("rp_iso_measured_mm"), a.get("rp_iso_predicted_mm")]
                    for m, a in c["position_accuracy"].items()]
            registered = any(a.get("ap_after_registration") for a in c["position_accuracy"].values())
            out += ["ISO 9283 position accuracy (means over the judged commanded positions, mm; RP, ISO 9283's "
                    "(the visits' mean distance from their mean + 3 sample standard deviations), over those "
                    "reached more than once; `|pred − meas| mean`: how far the method's predicted mean "
                    "attained position is from the measured one"
                    + ("; AP_P measured after each method's own registration (`frame: refit`): a constant offset "
                       "of the robot is absorbed in it, so it is not the standard's AP_P" if registered else "")
                    + "):", "",
                    table(["method", "positions", "AP_P measured", "AP_P predicted", "|pred − meas| mean",
                           "RP measured", "RP predicted"], rows), ""]
    return "\n".join(out)


def section_export(e: dict | None) -> str:
    out = ["## Exports for the robot cell", ""]
    if not e:
        return "\n".join(out + ["_reports/export.json not found (stage export)._", ""])
    rows = [[f"`{e['urdf']['file']}`", e["urdf"]["checked_with"], fmt(e["urdf"]["max_deviation_mm"], 2)]]
    if "ur_yaml" in e:
        rows.append([f"`{e['ur_yaml']['file']}`", e["ur_yaml"]["checked_with"],
                     fmt(e["ur_yaml"]["max_deviation_mm"], 2)])
    rows.append([f"`{e['onnx']['file']}`", e["onnx"]["checked_with"], fmt(e["onnx"]["max_deviation_mm"], 2)])
    out += ["Each file read back by an independent library (max deviation, mm, from the pipeline; "
            f"URDF and YAML on {e['n_poses']} poses, ONNX on {e['onnx']['n_test_poses']} test poses):", "",
            table(["file", "read by", "max deviation mm"], rows).rstrip(), ""]
    note = (f"The URDF is a rigid chain: fitted to the calibrated (elastic) model, it stays "
            f"{fmt(e['rigid_fit']['mean_mm'])} mm mean, {fmt(e['rigid_fit']['max_mm'])} mm max from it.")
    if "ur_yaml" in e:
        r = e["ur_yaml"]["not_held_after_joint_6"]
        note += (f" The UR YAML cannot hold the flange transform after joint 6 "
                 f"({fmt(r['translation_mm'])} mm, {fmt(r['rotation_deg'])}°).")
    return "\n".join(out + [note, ""])


def write_index(ctx, figs: dict, ply: dict) -> str:
    """index.md's text. ctx: the report stage's Context; figs: render_figures' result;
    ply: write_ply's."""
    m, s = ctx.metrics, ctx.summaries
    counts = ctx.pred.split.value_counts().to_dict()
    head = ["# SPI-BoTER calibration report", "",
            "Generated by `python -m pipeline.stages.report` (dvc stage `report`); open this page first.", ""]
    if "test" in m:
        t, p = m["test"]["3d"], PAPER_TEST["3d"]
        nom = (m.get("baselines") or {}).get("nominal_dh", {}).get("test", {}).get("3d")
        reported = m.get("reported") or {}
        if not reported.get("network", True):            # evaluate's verdict: the physics alone is served
            served = (m.get("baselines") or {}).get(reported.get("method"), {}).get("test", {}).get("3d")
            head += [f"**Served:** `{reported.get('method')}` (the network did not lower the validation error)"
                     + (f", test 3D MAE **{served['mae']:.4f} mm**" if served else "")
                     + "; the network's numbers follow.", ""]
        head += [f"**Summary:** model `{m.get('model', '?')}`, test 3D MAE **{t['mae']:.4f} mm**, "
                 f"RMSE {t['rmse']:.4f} mm, R² {fmt(t['r2'])} "
                 f"(paper: {p['mae']:.4f} / {p['rmse']:.4f} / {p['r2']:.4f})"
                 + (f"; uncompensated nominal DH on the same points: {nom['mae']:.4f} mm" if nom else "")
                 + ".", ""]
    skipped = [n for n, (st, _) in figs.items() if st != "ok"]
    head += ["Contents: settings · model metrics · comparison methods · data · calibration · "
             "training · compensation · validation · exports · ablation · point cloud · figures"
             + (f" (skipped: {', '.join(skipped)})" if skipped else ""), ""]
    parts = ["\n".join(head), section_settings(ctx.params, root=ctx.root),
             section_metrics(m, counts, root=ctx.root),
             section_baselines(m, ctx.baselines_md, root=ctx.root),
             section_data(s["ingest"], s["frame"], s["theory"], s["split"], counts, root=ctx.root),
             section_calibration(s["calibration"], root=ctx.root), section_parts(s["parts"], root=ctx.root),
             section_training(s["train"], root=ctx.root),
             section_compensation(s["compensation"], ctx.drive, root=ctx.root),
             section_validation(s["validation"], m.get("uncertainty")), section_export(s["export"]),
             section_ablation(),
             section_pointcloud(ply, root=ctx.root), section_figures(figs)]
    return "\n".join(p.rstrip() + "\n" for p in parts)

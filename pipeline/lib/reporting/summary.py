"""The one-page calibration summary a customer can be handed (issue 33): reports/summary.md and
reports/summary.pdf, one A4 page, the same text in both.

    blocks(inputs)               -> [block]: the page, built from what the report stage read
    markdown(blocks)             -> str
    write_pdf(blocks, path)      one A4 page; the same inputs give the same bytes

What it shows: the robot (model, DH convention, the marker offset), the instrument, the campaigns
(trained on, or independent), with their points, dates and temperature where the ingest table
recorded them; the accuracy on each (the training campaign's test split, each validation
campaign's judged points: mean / p95 / max 3D error for the nominal robot, the classical
calibration, the calibration with its error maps and the model); ISO 9283 AP_P / RP where a
campaign was commanded; and what the calibration does not cover. Every number is one of the
artifacts' (reports/*.json), or computed as they are from the predictions of the test split.

A block is ("h1" | "h2" | "p", text), ("table", header, rows) or ("list", [text]); text may hold
markdown's **bold** and `code`, which the PDF drops.
"""
import math
import re
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.lib.learning.metrics import stats
from pipeline.lib.project.columns import AXES, CAMPAIGN, MEAS, PRED, THEORY
from pipeline.lib.reporting.page import table

METHODS = {"nominal": "nominal", "calibrated": "calibration", "calibrated_parts": "calibration + error maps",
           "model": "model"}                                   # validation.json's names -> the page's
BASELINE_COLUMNS = {"calibrated": "calibrated_dh", "calibrated_parts": "calibrated_parts"}   # baselines.parquet
ROBOTS = {"ur5": "Universal Robots UR5", "ur10": "Universal Robots UR10"}
TIME_NAMES = ("timestamp", "time", "datetime", "date")        # a time column, until a setting names it
ORIENTATION = re.compile(r"(^|[_ ])(rx|ry|rz|roll|pitch|yaw)$", re.I)     # a measured orientation's headers ...
NOT_MEASURED = re.compile(r"goal|command|target|planned|std", re.I)     # ... not a commanded one's, nor its spread
NOT_RECORDED = "not recorded"
INSTRUMENT_SETTING = "summary.instrument"                       # params.yaml: what measured
A4_IN = (8.27, 11.69)
PDF_METADATA = {"Title": "Calibration summary", "Creator": "SPI-BoTER pipeline (python -m pipeline.stages.report)",
                "Producer": None, "CreationDate": None, "ModDate": None}   # nothing that changes between runs


# ------------------------------------------------------------------ numbers and their formats

def mm(v) -> str:
    """A length, mm, to the micrometre; "–" when there is none."""
    return "–" if v is None or not math.isfinite(v) else f"{v:.3f}"


def pct(share) -> str:
    return "–" if share is None else f"{100 * share:.0f}%"


def triple(st: dict | None) -> str:
    """mean / p95 / max (mm) of a stats dict."""
    return "–" if not st or st.get("mean") is None else " / ".join(mm(st[k]) for k in ("mean", "p95", "max"))


def split_accuracy(pred: pd.DataFrame, baselines: pd.DataFrame | None, split: str = "test") -> dict:
    """{campaign (and "all" with several): {"n", method: stats}} of the 3D error on `split`: nominal DH
    (theory), the calibration and the calibration with its maps (baselines.parquet, where the baselines
    stage wrote them) and the model (predictions.parquet)."""
    d = pred[pred.split == split]
    if baselines is not None:
        d = d.merge(baselines, on="point_id", how="left")
    meas = d[MEAS].to_numpy()
    err = {"nominal": np.linalg.norm(d[THEORY].to_numpy() - meas, axis=1),
           "model": np.linalg.norm(d[PRED].to_numpy() - meas, axis=1)}
    for m, col in BASELINE_COLUMNS.items():
        cols = [f"{col}_{a}" for a in AXES]
        if set(cols) <= set(d.columns) and d[cols].notna().all().all():
            err[m] = np.linalg.norm(d[cols].to_numpy() - meas, axis=1)
    camp = d[CAMPAIGN].to_numpy() if CAMPAIGN in d else np.full(len(d), "main")
    groups = {c: camp == c for c in dict.fromkeys(camp)}
    if len(groups) > 1:
        groups["all"] = np.ones(len(d), bool)
    return {c: {"n": int(k.sum()), **{m: stats(e[k]) for m, e in err.items()}} for c, k in groups.items()}


def split_counts(pred: pd.DataFrame) -> dict:
    """{campaign: {split: points}} of the predictions table (split.json's per_campaign, where that is missing)."""
    camp = pred[CAMPAIGN] if CAMPAIGN in pred else pd.Series("main", index=pred.index)
    return {c: {k: int(v) for k, v in g.split.value_counts().items()} for c, g in pred.groupby(camp, sort=False)}


# ------------------------------------------------------------------ dates and temperatures

def time_column(names) -> str | None:
    """The ingest table's time column: the first whose name is a TIME_NAMES one (case, spaces and
    underscores ignored)."""
    norm = {re.sub(r"[^a-z]", "", str(n).lower()): n for n in names}
    return next((norm[t] for t in TIME_NAMES if t in norm), None)


def orientation_columns(names) -> list:
    """The headers of a measured orientation among the ingest table's (not a commanded one's)."""
    return [c for c in names if ORIENTATION.search(str(c)) and not NOT_MEASURED.search(str(c))]


def _compact_date(v: float) -> str | None:
    """A YYYYMMDD[hhmmss] number as a date, to the precision it kept (a spreadsheet's 2,02011E+13 kept
    the month: 2020-11)."""
    digits = f"{int(round(v)):d}"
    if len(digits) not in (8, 14):
        return None
    y, m, d = int(digits[:4]), int(digits[4:6]), int(digits[6:8])
    if not 1900 <= y <= 2200 or m > 12 or d > 31:
        return None
    return f"{y:04d}" if m == 0 else f"{y:04d}-{m:02d}" if d == 0 else f"{y:04d}-{m:02d}-{d:02d}"


def date_range(values) -> str | None:
    """The first and last date of a time column (compact YYYYMMDD[hhmmss] numbers, or text a date
    parser reads), "first – last" or one date; None when the column holds neither."""
    s = pd.Series(values).dropna()
    if not len(s):
        return None
    if pd.api.types.is_numeric_dtype(s):
        lo, hi = _compact_date(float(s.min())), _compact_date(float(s.max()))
    else:
        t = pd.to_datetime(s.astype(str), errors="coerce", format="mixed")
        if t.isna().any():
            return None
        lo, hi = t.min().strftime("%Y-%m-%d"), t.max().strftime("%Y-%m-%d")
    if lo is None or hi is None:
        return None
    return lo if lo == hi else f"{lo} – {hi}"


def conditions(table: pd.DataFrame | None, temperature: str | None) -> dict:
    """Per campaign of the ingest table: {"dates": str | None, "t_min", "t_max", "t_mean" (°C) or None};
    `temperature`: the column parts.thermal.column names (None: not recorded)."""
    if table is None or CAMPAIGN not in table:
        return {}
    tcol = time_column([c for c in table.columns if c != temperature])
    out = {}
    for name, g in table.groupby(CAMPAIGN, sort=False):
        T = pd.to_numeric(g[temperature], errors="coerce").dropna() if temperature in g else pd.Series([], dtype=float)
        out[name] = {"dates": date_range(g[tcol]) if tcol else None,
                     **({"t_min": float(T.min()), "t_max": float(T.max()), "t_mean": float(T.mean())}
                        if len(T) else {"t_min": None, "t_max": None, "t_mean": None})}
    return out


def temperature_text(c: dict | None) -> str:
    if not c or c.get("t_mean") is None:
        return NOT_RECORDED
    lo, hi = f"{c['t_min']:.1f}", f"{c['t_max']:.1f}"
    return f"{lo} °C" if lo == hi else f"{lo}–{hi} °C"


# ------------------------------------------------------------------ the page

def robot_text(robot: dict, frame: dict | None, estimate_tool: bool) -> list:
    """The robot's and the measured point's lines."""
    name = ROBOTS.get(robot["model"], f"`{robot['model']}`")
    dh = ("the vendor's nominal DH table" if robot["model"] != "custom" else
          "its own DH table (`robot.dh`), given in modified DH (Craig) and converted"
          if (robot.get("dh") or {}).get("convention") == "modified" else "its own DH table (`robot.dh`)")
    tool = (frame or {}).get("tool_mm", robot["tool_mm"])
    how = "estimated with the base frame" if estimate_tool else "as set in `robot.tool_mm`"
    return [f"**Robot:** {name} (`robot.model: {robot['model']}`); standard Denavit-Hartenberg convention, "
            f"T_i = Rz(θ_i + offset_i) Tz(d_i) Tx(a_i) Rx(α_i), from {dh}.",
            f"**Measured point:** a marker at ({', '.join(f'{v:.3f}' for v in tool)}) mm in the flange frame "
            f"({how})."]


def method_text(metrics: dict, calibration: dict | None, parts: dict | None) -> str:
    identified = (calibration or {}).get("identified", [])
    elastic = not calibration or any(re.fullmatch(r"c\d", p) for p in identified)    # a joint's compliance identified
    kind = "elasto-geometric" if elastic else "geometric"
    cal = (f"classical {kind} calibration ({len(identified)} of {calibration.get('n_candidates')} parameters "
           f"identified)" if calibration else f"classical {kind} calibration")
    maps = ("" if parts is None else
            ", per-joint error maps (" + ("on" if parts.get("enabled") else
                                          "off: they did not lower the validation error") + ")")
    reported = metrics.get("reported") or {}
    if reported.get("network", True):
        return (f"**Calibration:** {cal}{maps}, and the SPI-BoTER network on top "
                f"(`{metrics.get('model', 'model')}`).")
    return (f"**Calibration:** {cal}{maps}; the SPI-BoTER network (`{metrics.get('model', 'model')}`) did not "
            f"lower the validation error and is not served: the robot cell gets `{reported.get('method')}`.")


def campaign_rows(trained: list, counts: dict, ingest: dict | None, cond: dict, validation: dict) -> list:
    """The campaigns table: role, points (kept / dropped), dates, temperature."""
    ing = (ingest or {}).get("campaigns") or {}
    rows = []
    for c in trained:
        n = counts.get(c) or {}
        kept = int(sum(n.values()))
        read = (ing.get(c) or {}).get("n_kept")
        at_ingest = (ing.get(c) or {}).get("n_dropped", 0)
        outliers = (read - kept) if read is not None else None
        split = " / ".join(f"{k} {n[k]}" for k in ("train", "val", "test", "holdout") if n.get(k))
        dropped = (f"{at_ingest + outliers} ({at_ingest} at ingest, {outliers} frame outliers)"
                   if outliers is not None else "–")
        rows.append([f"`{c}`", f"trained on ({split})", f"{kept} / {dropped}",
                     (cond.get(c) or {}).get("dates") or NOT_RECORDED, temperature_text(cond.get(c))])
    for c, v in validation.items():
        frame = {"same": "training frame", "refit": f"frame refit on {v['n_register']} points",
                 "refit_tool": f"frame and probe refit on {v['n_register']} points"}.get(v["frame"], v["frame"])
        th = v.get("thermal")
        temp = (f"{th['temperature_c']:.1f} °C (mean; {th['dT_k']:+.1f} K)" if th else NOT_RECORDED)
        ing_v = v.get("ingest") or {}
        rows.append([f"`{c}`", f"independent ({frame})",
                     f"{ing_v.get('n_kept', v['n'])} / {len(ing_v.get('dropped') or [])}", NOT_RECORDED, temp])
    return rows


def accuracy_rows(test: dict, validation: dict) -> list:
    rows = []
    for c, s in test.items():
        label = "all trained campaigns" if c == "all" else f"`{c}`"
        rows.append([f"{label}, test split", str(s["n"])] + [triple(s.get(m)) for m in METHODS])
    for c, v in validation.items():
        rows.append([f"`{c}`", str(v["n_judged"])]
                    + [triple({"mean": v["mean_3d_mm"].get(m), "p95": v["p95_3d_mm"].get(m),
                               "max": v["max_3d_mm"].get(m)}) for m in METHODS])
    return rows


def iso_rows(validation: dict) -> list:
    """Per commanded campaign: positions, AP_P (starred where measured after a registration to the model) and
    ISO 9283 RP measured (in the model's frame), and per method |predicted − measured| mean attained position."""
    rows = []
    for c, v in validation.items():
        pa = v.get("position_accuracy")
        if not pa:
            continue
        ref = pa.get("model") or next(iter(pa.values()))
        rows.append([f"`{c}`", f"{ref['positions']} ({ref.get('positions_repeated', 0)} repeated)",
                     mm(ref["ap_measured_mm"]) + (" *" if ref.get("ap_after_registration") else ""),
                     mm(ref.get("rp_iso_measured_mm"))]
                    + [mm((pa.get(m) or {}).get("bar_error_mm")) for m in METHODS])
    return rows


def not_covered(metrics: dict, validation: dict, cond: dict, trained: list, tool: list,
                orientation_columns: list) -> list:
    items = []
    u = (metrics.get("uncertainty") or {}).get("test") or {}
    ws = [f"{pct(1 - v['in_workspace_share'])} of `{c}`" for c, v in validation.items()
          if v.get("in_workspace_share") is not None]
    maps = [f"{pct(1 - v['angle_map']['in_range_share'])} of `{c}`" for c, v in validation.items()
            if (v.get("angle_map") or {}).get("in_range_share") is not None]
    items.append("**Poses outside the trained workspace.** The network corrects only near the joint "
                 "configurations it was trained on; elsewhere the model is its calibration. Outside it: "
                 + ", ".join(([f"{pct(1 - u['in_workspace_share'])} of the test split"]
                              if u.get("in_workspace_share") is not None else []) + ws)
                 + (" (outside the error maps' joint-angle range: " + ", ".join(maps) + ")" if maps else "") + ".")
    pose = (metrics.get("pose") or {}).get((metrics.get("reported") or {}).get("method"), {}).get("test")
    if pose:
        tcps = ", ".join(f"`{k}` {v['mean_mm']:.3f} mm" for k, v in pose["tcp"].items())
        items.append(f"**Orientation and tools.** Calibrated on the probe's position and orientation: on the test "
                     f"split the orientation is off by {pose['orientation']['mean_arcsec']:.0f}″ on average "
                     f"(95% within {pose['orientation']['p95_arcsec']:.0f}″)"
                     + (f"; at the tools (TCP) {tcps} mean." if tcps else "; no TCP is set (`robot.tcp`)."))
    else:
        items.append("**Orientation.** Only the marker's position is calibrated and judged; the tool's "
                     "orientation accuracy is not stated"
                     + (f" (the tracker recorded {', '.join(f'`{c}`' for c in orientation_columns[:3])}"
                        f"{', …' if len(orientation_columns) > 3 else ''}, not used)." if orientation_columns
                        else " (no orientation was measured)."))
    temps = [(c, cond.get(c)) for c in trained if (cond.get(c) or {}).get("t_mean") is not None]
    if temps:
        lo = min(t["t_min"] for _, t in temps)
        hi = max(t["t_max"] for _, t in temps)
        out = [f"`{c}` at {v['thermal']['temperature_c']:.1f} °C" for c, v in validation.items()
               if v.get("thermal") and not lo <= v["thermal"]["temperature_c"] <= hi]
        items.append(f"**Temperature.** Trained at {lo:.1f}–{hi:.1f} °C; elsewhere only the links' thermal "
                     "expansion is modelled, the accuracy is not established"
                     + (f" (judged outside that range: {', '.join(out)})." if out else "."))
    else:
        items.append("**Temperature.** Not recorded: the accuracy holds at the campaign's (unknown) "
                     "temperature; at another, it is not established.")
    items.append(f"**The tool.** Only the measurement marker at ({', '.join(f'{v:.3f}' for v in tool)}) mm in "
                 "the flange frame is calibrated; a working tool's own offset and errors are not.")
    refit = [f"`{c}` ({v['n_register']} points{', probe offset too' if v['frame'] == 'refit_tool' else ''})"
             for c, v in validation.items() if v["frame"] != "same"]
    if refit:
        items.append("**Where the robot stands.** Registered on its own points (frame refit): " + ", ".join(refit)
                     + ". Those numbers judge the arm, not where its base sits in the cell: that is measured "
                     "again at each set-up.")
    if not validation:
        items.append("**Independent campaigns.** None was measured: the accuracy above is the trained "
                     "campaign's own test split, under its conditions.")
    return items


def blocks(params: dict, metrics: dict, s: dict, test: dict, cond: dict, orientation_columns: list,
           counts: dict | None = None) -> list:
    """The page. params: the report stage's (robot, campaigns, frame, parts, validate); metrics:
    reports/metrics.json; s: the stage summaries by name (report.SUMMARIES; None when missing); test:
    split_accuracy's; cond: conditions'; orientation_columns: the ingest table's orientation headers;
    counts: split_counts' (used where reports/split.json is missing)."""
    frame = s.get("frame")
    validation = ((s.get("validation") or {}).get("campaigns") or {})
    split = s.get("split") or {}
    counts = split.get("per_campaign") or counts or {}
    trained = list(counts) or list((metrics.get("campaigns") or {})) or [params["campaigns"]["name"]]
    tool = (frame or {}).get("tool_mm", params["robot"]["tool_mm"])
    out = [("h1", f"Calibration summary: {ROBOTS.get(params['robot']['model'], params['robot']['model'])}")]
    out += [("p", x) for x in robot_text(params["robot"], frame, params["frame"]["estimate_tool"])]
    instrument = params["summary"]["instrument"]
    out += [("p", f"**Instrument:** {instrument}." if instrument else
             f"**Instrument:** {NOT_RECORDED} (set `{INSTRUMENT_SETTING}`)."),
            ("p", method_text(metrics, s.get("calibration"), s.get("parts"))),
            ("h2", "Campaigns"),
            ("table", ["campaign", "role", "points kept / dropped", "dates", "temperature"],
             campaign_rows(trained, counts, s.get("ingest"), cond, validation)),
            ("h2", "Accuracy: 3D error of the marker, mm (mean / p95 / max)"),
            ("table", ["campaign", "points"] + list(METHODS.values()), accuracy_rows(test, validation)),
            ("p", "The test split is the trained campaign's own (random 8:1:1 split, never trained on); an "
                  "independent campaign was measured apart and never trained on. Nominal: the vendor's DH table "
                  "in the same frame.")]
    iso = iso_rows(validation)
    commanded = [c for c, v in params["validate"]["campaigns"].items() if (v or {}).get("commanded")]
    if iso:
        out += [("h2", "ISO 9283 position accuracy (commanded positions, mm)"),
                ("table", ["campaign", "positions", "AP_P", "RP"] + list(METHODS.values()), iso),
                ("p", "AP_P and RP as measured (means over the commanded positions; RP, ISO 9283's: the visits' "
                      "mean distance from their mean plus three sample standard deviations, where a position was "
                      "reached more than once; * AP_P after a registration to the model's own prediction, "
                      "`frame: refit`: a constant offset of the robot is absorbed there). Under each method: how "
                      "far its predicted mean attained position is from the measured one (mean over the "
                      "positions), about the AP_P left where that method compensates the commands.")]
    else:
        out += [("p", "**ISO 9283 AP_P / RP:** " + ("not computed" if commanded else
                                                   "no campaign was commanded (`validate.campaigns.*.commanded`)")
                 + ".")]
    out += [("h2", "What the calibration does not cover"),
            ("list", not_covered(metrics, validation, cond, trained, tool, orientation_columns)),
            ("p", "Every number is this pipeline run's (reports/metrics.json, validation.json, ingest.json, "
                  "split.json, calibration.json, parts.json; the test split's p95 and max from its predictions); "
                  "written by `python -m pipeline.stages.report`.")]
    return out


# ------------------------------------------------------------------ markdown

def markdown(bl: list) -> str:
    out = []
    for b in bl:
        kind = b[0]
        if kind == "h1":
            out += [f"# {b[1]}", ""]
        elif kind == "h2":
            out += [f"## {b[1]}", ""]
        elif kind == "p":
            out += [b[1], ""]
        elif kind == "table":
            out += [table(b[1], b[2]).rstrip("\n"), ""]
        elif kind == "list":
            out += [f"- {x}" for x in b[1]] + [""]
    return "\n".join(out).rstrip() + "\n"


# ------------------------------------------------------------------ PDF

def plain(text: str) -> str:
    """Text without markdown's ** and backticks."""
    return text.replace("**", "").replace("`", "")


def _width(text: str, size: float, bold: bool = False) -> float:
    """The width of `text` in points at font size `size` (DejaVu Sans, matplotlib's default)."""
    from matplotlib.font_manager import FontProperties
    from matplotlib.textpath import text_to_path
    if not text.strip():
        return 0.0
    prop = FontProperties(family="DejaVu Sans", weight="bold" if bold else "normal", size=size)
    return float(text_to_path.get_text_width_height_descent(text, prop, ismath=False)[0])


def _wrap(text: str, size: float, width: float, bold: bool = False) -> list:
    lines, cur = [], ""
    for word in text.split(" "):
        trial = f"{cur} {word}" if cur else word
        if cur and _width(trial, size, bold) > width:
            lines.append(cur)
            cur = word
        else:
            cur = trial
    return lines + [cur]


def _layout(bl: list, size: float, width: float) -> tuple:
    """[(kind, x, dy, text, size, bold)] at base font `size` and the page height it takes (pt)."""
    items, y, lead = [], 0.0, 1.3 * size
    for b in bl:
        kind = b[0]
        if kind in ("h1", "h2"):
            s = size * (1.6 if kind == "h1" else 1.2)
            y += s * (0.6 if items else 0) + s * 1.3
            items.append(("text", 0.0, y, plain(b[1]), s, True))
            y += 0.25 * s
        elif kind == "p":
            for line in _wrap(plain(b[1]), size, width):
                y += lead
                items.append(("text", 0.0, y, line, size, False))
            y += 0.4 * size
        elif kind == "list":
            for x in b[1]:
                for k, line in enumerate(_wrap(plain(x), size, width - 10)):
                    y += lead
                    items.append(("text", 0.0, y, "•", size, False) if k == 0 else None)
                    items.append(("text", 10.0, y, line, size, False))
            y += 0.4 * size
        elif kind == "table":
            header, rows = [plain(h) for h in b[1]], [[plain(c) for c in r] for r in b[2]]
            ts = size * 0.9
            widths = [max([_width(header[k], ts, True)] + [_width(r[k], ts) for r in rows]) for k in range(len(header))]
            pad = 8.0
            scale = min(1.0, (width - pad * (len(header) - 1)) / sum(widths))
            ts *= scale
            widths = [w * scale for w in widths]
            xs = np.concatenate([[0.0], np.cumsum([w + pad for w in widths])[:-1]])
            y += 1.3 * ts
            items += [("text", float(x), y, h, ts, True) for x, h in zip(xs, header)]
            items.append(("rule", 0.0, y + 0.35 * ts, "", float(xs[-1] + widths[-1]), False))
            for r in rows:
                y += 1.3 * ts
                items += [("text", float(x), y, c, ts, False) for x, c in zip(xs, r)]
            y += 0.6 * size
    return [i for i in items if i is not None], y


def write_pdf(bl: list, path: Path) -> dict:
    """The page as one A4 PDF page at `path`, the font shrunk until it fits; byte-reproducible (no
    dates, no version strings in its metadata). Returns {"font_pt", "pages": 1}."""
    import matplotlib
    from matplotlib.lines import Line2D
    from matplotlib.backends.backend_pdf import PdfPages
    from matplotlib.figure import Figure
    margin = 48.0                                              # pt (2/3 in)
    W, H = A4_IN[0] * 72, A4_IN[1] * 72
    for size in np.arange(9.0, 4.9, -0.25):
        items, height = _layout(bl, float(size), W - 2 * margin)
        if height <= H - 2 * margin:
            break
    with matplotlib.rc_context({"pdf.fonttype": 3, "font.family": "DejaVu Sans", "pdf.compression": 6}):
        fig = Figure(figsize=A4_IN)
        for kind, x, y, text, s, bold in items:
            fx, fy = (margin + x) / W, 1 - (margin + y) / H
            if kind == "rule":
                fig.add_artist(Line2D([fx, (margin + x + s) / W], [fy, fy], lw=0.5, color="0.3",
                                      transform=fig.transFigure))
            else:
                fig.text(fx, fy, text, fontsize=s, fontweight="bold" if bold else "normal", va="baseline")
        path.parent.mkdir(parents=True, exist_ok=True)
        with PdfPages(path, metadata=PDF_METADATA) as pdf:
            pdf.savefig(fig)
    return {"font_pt": float(size), "pages": 1}

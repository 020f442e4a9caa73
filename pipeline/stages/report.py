"""Stage report: figures, a reviewer's index page, a coloured point cloud and a customer's summary.

    reports/plots/<name>.png   one PNG per entry of lib/reporting/figures.py FIGURES
    reports/index.md           lib/reporting/page.py: settings, metrics beside the paper's, data / frame /
                               calibration / compensation summaries, the figures
    reports/points_error.ply   measured points (base frame, mm) coloured by |pred - meas|
    reports/summary.md, .pdf   lib/reporting/summary.py: the one-page calibration summary a customer can be
                               handed (robot, campaigns, accuracy per campaign, ISO 9283 where
                               commanded, what the calibration does not cover); one A4 page, the
                               same bytes for the same inputs

Required inputs: data/interim/predictions.parquet and reports/metrics.json.
Every other input is optional; a figure or section whose input is missing is
skipped with a note in index.md (and in the log). The opt-in ablation's outputs
(`python -m pipeline.commands.ablation`) are linked from index.md, never read.
"""
from functools import cached_property
from pathlib import Path

import pandas as pd

import pyarrow.parquet as pq

from pipeline.lib.learning.checkpoint import load_model
from pipeline.lib.project.artifacts import (BASELINES_MD, BASELINES_TABLE, CALIBRATION_JSON, COMPENSATION_JSON,
                                            CONVERGENCE_CSV, DRIVE_CSV, EXPORT_JSON, FRAME_JSON, HERE, INGEST_JSON,
                                            INGEST_TABLE, LIVE, METRICS_JSON, MODEL_WEIGHTS, PARTS_REPORT,
                                            PREDICTIONS_TABLE, REPORTS, SPLIT_JSON, THEORY_JSON, TRAIN_JSON,
                                            VALIDATION_JSON, VALIDATION_TABLE)
from pipeline.lib.project.cli import script, stage_main
from pipeline.lib.project.columns import MEAS, PRED, THEORY
from pipeline.lib.project.config import for_stage, logger, read_json
from pipeline.lib.reporting import figures, page, summary

log = logger(__name__)
PARAMS = ("robot", "ingest", "campaigns", "frame", "split", "calibrate", "parts", "model", "loss", "train", "baselines",
          "workspace", "compensate", "validate", "ablation", "summary")      # the settings the page shows, and compensate's

PLOTS = REPORTS / "plots"
INDEX = REPORTS / "index.md"
PLY = REPORTS / "points_error.ply"
SUMMARY_MD, SUMMARY_PDF = REPORTS / "summary.md", REPORTS / "summary.pdf"
CURVES = LIVE / "plots" / "metrics"          # dvclive's per-epoch curves
SUMMARIES = {"ingest": INGEST_JSON, "frame": FRAME_JSON, "theory": THEORY_JSON, "parts": PARTS_REPORT,
             "split": SPLIT_JSON, "calibration": CALIBRATION_JSON,
             "train": TRAIN_JSON, "compensation": COMPENSATION_JSON, "validation": VALIDATION_JSON,
             "export": EXPORT_JSON}


def optional_json(path: Path):
    return read_json(path) if path.exists() else None


def optional_csv(path: Path) -> pd.DataFrame | None:
    """The table at `path`, or None if it is missing or has no rows."""
    if not path.exists():
        return None
    df = pd.read_csv(path)
    return df if len(df) else None


class Context:
    """The run's inputs, read on first use; an optional one is None when missing."""

    def __init__(self, params: dict, root: Path = HERE):
        self.params, self.root = params, root
        self.pred = pd.read_parquet(root / PREDICTIONS_TABLE)
        self.metrics = read_json(root / METRICS_JSON)
        missing = [c for c in ["point_id", "split"] + THEORY + MEAS + PRED if c not in self.pred]
        if missing:
            raise ValueError(f"{PREDICTIONS_TABLE}: missing column(s) {missing}")

    @cached_property
    def summaries(self) -> dict:
        """Each stage's JSON summary by SUMMARIES name."""
        return {name: optional_json(self.root / path) for name, path in SUMMARIES.items()}

    @cached_property
    def baselines_md(self) -> str | None:
        path = self.root / BASELINES_MD
        return path.read_text() if path.exists() else None

    @cached_property
    def convergence(self):
        return optional_csv(self.root / CONVERGENCE_CSV)

    @cached_property
    def drive(self):
        return optional_csv(self.root / DRIVE_CSV)

    @cached_property
    def validation(self) -> pd.DataFrame | None:
        """reports/validation.parquet (every campaign's points), None when missing."""
        path = self.root / VALIDATION_TABLE
        return pd.read_parquet(path) if path.exists() else None

    @cached_property
    def baseline_predictions(self) -> pd.DataFrame | None:
        """data/interim/baselines.parquet (the calibration's, and with its maps, predictions), None when missing."""
        path = self.root / BASELINES_TABLE
        return pd.read_parquet(path) if path.exists() else None

    @cached_property
    def ingest_table(self) -> pd.DataFrame | None:
        """Of data/interim/ingest.parquet, the columns the summary shows: campaign, the temperature
        (parts.thermal.column) and a time column; None when missing. attrs["all_columns"]: every header."""
        path = self.root / INGEST_TABLE
        if not path.exists():
            return None
        names = pq.read_schema(path).names
        temperature = self.params["parts"]["thermal"]["column"]
        want = [c for c in dict.fromkeys(["campaign", temperature, summary.time_column(names)]) if c in names]
        df = pd.read_parquet(path, columns=want)
        df.attrs["all_columns"] = names
        return df

    def write_summary(self) -> dict:
        """reports/summary.md and reports/summary.pdf (lib/reporting/summary.py)."""
        table = self.ingest_table
        names = table.attrs.get("all_columns", []) if table is not None else []
        blocks = summary.blocks(self.params, self.metrics, self.summaries,
                                summary.split_accuracy(self.pred, self.baseline_predictions),
                                summary.conditions(table, self.params["parts"]["thermal"]["column"]),
                                summary.orientation_columns(names), summary.split_counts(self.pred))
        (self.root / SUMMARY_MD).write_text(summary.markdown(blocks))
        return summary.write_pdf(blocks, self.root / SUMMARY_PDF)

    @cached_property
    def model(self):
        path = self.root / MODEL_WEIGHTS
        return load_model(path) if path.exists() else None

    def live(self, name: str) -> pd.DataFrame | None:
        """A dvclive curve: columns step, <name>."""
        path = self.root / CURVES / f"{name}.tsv"
        if not path.exists():
            return None
        df = pd.read_csv(path, sep="\t")
        return df if {"step", name} <= set(df.columns) and df[name].notna().any() else None


def run(params: dict, root: Path = HERE) -> dict:
    ctx = Context(for_stage(params, PARAMS), root)
    figs = {n: (st, Path(x).relative_to(root) if st == "ok" else x)              # the page links them
            for n, (st, x) in figures.render_figures(ctx, root / PLOTS).items()}
    ply = figures.write_ply(ctx, root / PLY)
    ply["path"] = Path(ply["path"]).relative_to(root)
    (root / INDEX).write_text(page.write_index(ctx, figs, ply))
    sheet = ctx.write_summary()
    made = [n for n, (s, _) in figs.items() if s == "ok"]
    log.info("wrote %d figures to %s (%d skipped), %s, %s (%d points, colour 0-%.3f mm), %s and %s (%.2f pt)",
             len(made), PLOTS, len(figs) - len(made), INDEX, PLY, ply["n"], ply["hi"], SUMMARY_MD, SUMMARY_PDF,
             sheet["font_pt"])
    return {"figures": {n: s for n, (s, _) in figs.items()}, "ply_points": ply["n"],
            "ply_scale_mm": [ply["lo"], ply["hi"]], "summary": sheet}


main = stage_main(__spec__.name, __doc__, run)         # main(argv=None, root=HERE)


if __name__ == "__main__":
    script(__spec__.name, main)

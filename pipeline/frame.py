"""Stage frame: fit the base-to-world (tracker) frame, P_world = R Q_base + t (eqs. 20-26).

Robust Kabsch on the nominal theory points (lib/frames.py), optionally with
the tool offset (`frame.estimate_tool`). Writes reports/frame.json
(DATA_FORMAT.md): R, t, rms_mm, n_used, outliers, plus tool_mm (the tool
offset every later stage uses) and fit diagnostics.
"""
import numpy as np
import pandas as pd

from .lib.artifacts import FRAME_JSON, INGEST_TABLE
from .lib.columns import JOINTS_DEG, MEAS
from .lib.config import load_params, logger, section, write_json
from .lib.frames import fit_frame
from .lib.robots import load_robot

log = logger(__name__)


def run(params: dict) -> dict:
    robot = load_robot(section(params, "robot"))
    df = pd.read_parquet(INGEST_TABLE)
    fit = fit_frame(df[JOINTS_DEG].to_numpy(), df[MEAS].to_numpy(), robot, section(params, "frame"))
    inl, r = fit["inliers"], fit["residual_mm"]
    outliers = df.loc[~inl, "point_id"].tolist()
    summary = {
        "R": fit["R"], "t": fit["t"],
        "rms_mm": float(np.sqrt(np.mean(r[inl] ** 2))),
        "n_used": int(inl.sum()),
        "outliers": outliers,
        "outlier_residual_mm": {p: round(float(v), 4) for p, v in zip(outliers, r[~inl])},
        "mean_mm": float(r[inl].mean()), "max_mm": float(r[inl].max()),
        "tool_mm": fit["tool_mm"], "method": fit["method"], "condition": fit["condition"],
        "det_R": float(np.linalg.det(fit["R"])),
    }
    write_json(FRAME_JSON, summary)
    log.info("fitted base frame (%s) on %d of %d points: rms %.4f mm, mean %.4f mm; "
             "%d outliers rejected %s; tool %s mm", fit["method"], inl.sum(), len(df),
             summary["rms_mm"], summary["mean_mm"], len(outliers), outliers,
             np.round(fit["tool_mm"], 3).tolist())
    return summary


if __name__ == "__main__":
    run(load_params())

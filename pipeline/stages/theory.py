"""Stage theory: nominal DH theory points (eq. 1) and measured points in the base frame.

theory = nominal DH + tool (tool from reports/frame.json: fixed or estimated; the point's
         station's own with frame.tool_per_station),
meas   = R^T (P_world - t) with the fitted frame of the point's station (inverse of eq. 20),
err    = meas - theory, what the network learns;
meas_q* = the measured orientation in the base frame, R^T R_world (where the campaign has it).
Points the frame fit rejected as gross outliers are dropped here and listed
in reports/theory.json with their residual.
"""
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.lib.project.artifacts import FRAME_JSON, HERE, INGEST_TABLE, POINTS_TABLE, THEORY_JSON
from pipeline.lib.project.cli import script, stage_main
from pipeline.lib.project.columns import CAMPAIGN, ERR, JOINTS_DEG, MEAS, MEAS_Q, STATION, THEORY
from pipeline.lib.project.config import for_stage, logger, read_json, write_json
from pipeline.lib.robot.frames import measured_rotations, quaternions, to_base
from pipeline.lib.robot.geometry import theory_geometry
from pipeline.lib.robot.kinematics import fk_numpy
from pipeline.lib.robot.robots import load_robot

log = logger(__name__)
PARAMS = ("robot",)


def run(params: dict, root: Path = HERE) -> dict:
    robot = load_robot(for_stage(params, PARAMS)["robot"])
    frame = read_json(root / FRAME_JSON)
    df = pd.read_parquet(root / INGEST_TABLE)
    out = df[["point_id", CAMPAIGN, STATION] + JOINTS_DEG].copy()
    theo, meas = np.full((len(df), 3), np.nan), np.full((len(df), 3), np.nan)
    for s, f in frame["stations"].items():           # the station's frame and tool (frame.tool_per_station)
        m = (df[STATION] == s).to_numpy()
        theo[m] = fk_numpy(df.loc[m, JOINTS_DEG].to_numpy(), robot, theory_geometry(robot, f["tool_mm"]))
        meas[m] = to_base(df.loc[m, MEAS].to_numpy(), f)
    out[THEORY], out[MEAS] = theo, meas
    out[ERR] = out[MEAS].to_numpy() - out[THEORY].to_numpy()
    R_world = measured_rotations(df)
    if R_world is not None:
        R_base = np.empty_like(R_world)
        for s, f in frame["stations"].items():
            m = (df[STATION] == s).to_numpy()
            R_base[m] = np.einsum("ji,njk->nik", np.asarray(f["R"]), R_world[m])
        out[MEAS_Q] = quaternions(R_base)
    bad = out["point_id"].isin(frame["outliers"])
    dropped = [{"point_id": p, "reason": "frame outlier",
                "residual_mm": frame["outlier_residual_mm"][p]} for p in out.loc[bad, "point_id"]]
    out = out[~bad].reset_index(drop=True)
    (root / POINTS_TABLE).parent.mkdir(parents=True, exist_ok=True)
    out.to_parquet(root / POINTS_TABLE, index=False)
    e = np.linalg.norm(out[ERR].to_numpy(), axis=1)
    summary = {"n_points": len(out), "n_dropped": len(dropped), "dropped": dropped,
               "nominal_error_mm": {"mean": float(e.mean()), "rms": float(np.sqrt((e ** 2).mean())),
                                    "max": float(e.max())},
               "campaigns": {c: {"n": int(m.sum()), "nominal_error_mean_mm": float(e[m].mean())}
                             for c in out[CAMPAIGN].unique() if (m := (out[CAMPAIGN] == c).to_numpy()).any()}}
    write_json(root / THEORY_JSON, summary)
    log.info("theory points for %d poses (%d frame outliers dropped); nominal DH error after "
             "frame fit: mean %.3f mm, max %.3f mm", len(out), len(dropped), e.mean(), e.max())
    return summary


main = stage_main(__spec__.name, __doc__, run)         # main(argv=None, root=HERE)

if __name__ == "__main__":
    script(__spec__.name, main)

"""Stage calibrate: classical kinematic calibration on the train split (lib/robot/identify.py).

Starts from nominal DH with the frame stage's tool, identifies the groups in
`calibrate.params` (DH errors, parallel-axis tilts, tool, base correction)
by robust least squares, fixing what the data cannot tell apart. With several
tracker stations, each further station's frame correction (and, with
frame.tool_per_station, its tool offset) is identified jointly (the robot's
parameters are shared). Writes models/calibration.json (the geometry, and the
station corrections that map every station's points into the first station's
base frame and tool: lib/robot/geometry.py aligned) and
reports/calibration.json (the identification report and the error per split
and per campaign, nominal vs calibrated, on the aligned points).
"""
from pathlib import Path

import numpy as np
import torch

from pipeline.lib.project.artifacts import (CALIBRATED_GEOMETRY, CALIBRATION_JSON, FRAME_JSON, HERE, TIMINGS,
                                            load_points)
from pipeline.lib.project.cli import script, stage_main
from pipeline.lib.project.columns import CAMPAIGN, JOINTS_DEG, MEAS, SPLITS, STATION
from pipeline.lib.project.config import for_stage, logger, read_json, split_timings, write_json
from pipeline.lib.robot.frames import measured_rotations
from pipeline.lib.robot.geometry import Calibration, aligned, theory_geometry
from pipeline.lib.robot.identify import errors_3d, identify, orientation_errors
from pipeline.lib.robot.kinematics import DTYPE, fk_pose, save_geometry
from pipeline.lib.robot.robots import load_robot

log = logger(__name__)
PARAMS = ("robot", "frame", "calibrate")


def run(params: dict, root: Path = HERE) -> dict:
    params = for_stage(params, PARAMS)
    cfg = params["calibrate"]
    frame = read_json(root / FRAME_JSON)
    pts = load_points(root)
    q = np.radians(pts[JOINTS_DEG].to_numpy())
    stations = list(pts[STATION].unique())            # theory keeps the ingest order: the first station first
    train = (pts["split"] == "train").to_numpy()
    g0 = theory_geometry(load_robot(params["robot"]), frame["tool_mm"], frame.get("tool_rot"))
    R_meas = measured_rotations(pts)                  # the probe's measured orientations (base frame), or None
    station = pts[STATION].map({s: k for k, s in enumerate(stations)}).to_numpy()
    tools0 = None                                     # frame.tool_per_station: each station's tool - the first's
    if params["frame"]["tool_per_station"]:
        fr = frame["stations"]
        tools0 = np.array([fr[s]["tool_mm"] for s in stations]) - np.asarray(fr[stations[0]]["tool_mm"])
    geometry, report = identify(q[train], pts[MEAS].to_numpy()[train], g0, cfg, station[train], stations,
                                tools0, None if R_meas is None else R_meas[train])
    corrections = {k: report[k] for k in ("stations", "station_tools")}
    at_first = aligned(pts, Calibration(geometry, **corrections), g0)
    p, R_first = at_first[MEAS].to_numpy(), measured_rotations(at_first)
    qt = torch.as_tensor(q, dtype=DTYPE)
    with torch.no_grad():
        (p_cal, R_cal), (p_nom, R_nom) = ((v.numpy() for v in fk_pose(qt, g)) for g in (geometry, g0))

    def judged(pp, RR, k):
        e = errors_3d(pp[k], p[k])
        return e if R_first is None else {**e, "orientation": orientation_errors(RR[k], R_first[k])}

    def errors(m):                                    # per split of the points m
        return {s: {"n": int(k.sum()), "calibrated": judged(p_cal, R_cal, k), "nominal": judged(p_nom, R_nom, k)}
                for s in SPLITS if (k := m & (pts["split"] == s).to_numpy()).any()}
    report["splits"] = errors(np.ones(len(pts), bool))
    report["campaigns"] = {c: errors((pts[CAMPAIGN] == c).to_numpy()) for c in pts[CAMPAIGN].unique()}
    save_geometry(root / CALIBRATED_GEOMETRY, geometry, {"robot": params["robot"]["model"],
                                                "identified": report["identified"],
                                                **corrections})
    report, timings = split_timings(report)
    write_json(root / CALIBRATION_JSON, report)
    write_json(root / TIMINGS / "calibrate.json", timings)
    sp = report["splits"]
    last = sp.get("test", sp["train"])
    log.info("identified %d of %d parameters (fixed %s) in %.1f s, %d evaluations; cond %.3g; "
             "mean 3D error train %.4f -> %.4f mm, test %.4f -> %.4f mm",
             len(report["identified"]), report["n_candidates"], sorted(report["fixed"]),
             timings["seconds"], report["nfev"], report["condition_number"],
             sp["train"]["nominal"]["mean_mm"], sp["train"]["calibrated"]["mean_mm"],
             last["nominal"]["mean_mm"], last["calibrated"]["mean_mm"])
    return report


main = stage_main(__spec__.name, __doc__, run)         # main(argv=None, root=HERE)

if __name__ == "__main__":
    script(__spec__.name, main)

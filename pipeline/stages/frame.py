"""Stage frame: fit the base-to-world (tracker) frame, P_world = R Q_base + t (eqs. 20-26).

Robust Kabsch on the nominal theory points (lib/robot/frames.py), one frame per
tracker station (the `station` column; campaigns.station / campaigns.more),
optionally refined jointly with the tool offset (`frame.estimate_tool`): one
shared by every station, or one per station (`frame.tool_per_station`).
Writes reports/frame.json (docs/data-format.md): R, t, rms_mm, n_used of the first
station (the base frame the later stages work in), outliers of every station,
tool_mm (the first station's tool offset: the one the model predicts), fit
diagnostics (with estimate_tool, tool_held: the tool components the poses cannot determine, held at
robot.tool_mm), and under "stations" every station's frame, tool and fit. Where the campaign
measures orientation: tool_rot, the probe's rotation in the flange (lib/robot/frames.py probe_rotation,
per station), and the scatter of the measured orientations about it.
"""
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.lib.project.artifacts import FRAME_JSON, HERE, INGEST_TABLE
from pipeline.lib.project.cli import script, stage_main
from pipeline.lib.project.columns import CAMPAIGN, JOINTS_DEG, MEAS, STATION
from pipeline.lib.project.config import for_stage, logger, write_json
from pipeline.lib.robot.frames import (MISREAD_PERCENTILE, FrameFitError, fit_frames, flange_poses, measured_rotations,
                                       probe_rotation)
from pipeline.lib.robot.kinematics import nominal_geometry
from pipeline.lib.robot.robots import load_robot

log = logger(__name__)
PARAMS = ("robot", "frame")


def fit_stats(r: np.ndarray, inl: np.ndarray) -> dict:
    return {"rms_mm": float(np.sqrt(np.mean(r[inl] ** 2))), "n_used": int(inl.sum()),
            "mean_mm": float(r[inl].mean()), "max_mm": float(r[inl].max())}


def orientation_fit(Rf: np.ndarray, R_world: np.ndarray, R: np.ndarray, k: float) -> tuple[dict, np.ndarray]:
    """The probe's rotation in the flange for one station's poses (flange rotations Rf, measured
    orientations R_world in the tracker frame, the station's frame rotation R), with its scatter; and each
    pose's scatter about it (n,) arcsec."""
    R_tool, rxyz, inl, dev = probe_rotation(Rf, np.einsum("ji,njk->nik", R, R_world), k)
    return {"tool_rot": rxyz, "tool_R": R_tool, "orientation_n_used": int(inl.sum()),
            "orientation_scatter_arcsec": {"mean": float(dev[inl].mean()), "median": float(np.median(dev)),
                                           "max": float(dev.max())}}, dev


def check_orientations(dev: np.ndarray, campaigns: np.ndarray, station: str, limit: float) -> None:
    """Stop where a campaign's measured orientations scatter more than `limit` arcsec (the MISREAD_PERCENTILE of
    its poses' dev (n,), each pose's campaign (n,)) about its station's fitted probe rotation: no arm's kinematic
    error turns its flange that far (nominal DH: the IPA UR10 261 arcsec mean, the twin 1046), misread
    orientation columns do (the IPA T-Mac's read in another Euler convention: 35000-100000 on most of a
    campaign, on half of it where two of its angles are alike), and a misread campaign beside a read one,
    which the robust fit leaves out of the station's own scatter."""
    at = {c: float(np.percentile(dev[campaigns == c], MISREAD_PERCENTILE)) for c in dict.fromkeys(campaigns)}
    off = [c for c, v in at.items() if v > limit]
    if off:
        which = f"{MISREAD_PERCENTILE}th percentile"
        each = ", ".join(f"{c} {v:.0f}" for c, v in at.items())
        raise FrameFitError(f"campaign {off[0]} (station {station}): its measured orientations scatter "
                            f"{at[off[0]]:.0f} arcsec ({which}) about the probe's fitted rotation in the flange, "
                            f"above frame.max_orientation_scatter_arcsec = {limit:g} (each campaign's {which}: "
                            f"{each}): "
                            "orientation columns are misread, its own or, where the others are off too, theirs. "
                            "Check ingest.orientation (the Euler sequence, intrinsic XYZ or extrinsic xyz, and "
                            "angle_unit; a quaternion's scalar_first) and, for a multi-marker target, that every "
                            "campaign shares its geometry (ingest.target)")


def run(params: dict, root: Path = HERE) -> dict:
    p = for_stage(params, PARAMS)
    robot = load_robot(p["robot"])
    df = pd.read_parquet(root / INGEST_TABLE)
    fit = fit_frames(df[JOINTS_DEG].to_numpy(), df[MEAS].to_numpy(), df[STATION].to_numpy(), robot, p["frame"])
    inl, r = fit["inliers"], fit["residual_mm"]
    outliers = df.loc[~inl, "point_id"].tolist()
    R_world = measured_rotations(df)
    probe_tcps = [n for n, c in (p["robot"]["tcp"] or {}).items() if c.get("frame", "flange") == "probe"]
    if R_world is None and probe_tcps:                     # the export would stop on it, eight stages on
        raise FrameFitError(f"robot.tcp {probe_tcps[0]}: given in the probe's frame (frame: probe), but the campaign "
                            f"measures no orientation ({root / INGEST_TABLE} has no meas_q*), so the probe's rotation "
                            "in the flange is never fitted: give it in the flange frame, or read the orientation "
                            "(ingest.columns.orientation or ingest.columns.marker)")
    Rf = None if R_world is None else flange_poses(df[JOINTS_DEG].to_numpy(), nominal_geometry(robot))[0]
    stations = {}
    for s, f in fit["stations"].items():
        m = f["points"]
        stations[s] = {"R": f["R"], "t": f["t"], "tool_mm": f["tool_mm"], **fit_stats(r[m], inl[m]), "n": int(m.sum()),
                       "campaigns": sorted(df.loc[m, CAMPAIGN].unique()),
                       "outliers": df.loc[m & ~inl, "point_id"].tolist()}
        if R_world is not None:
            k = m & inl
            fitted, dev = orientation_fit(Rf[k], R_world[k], np.asarray(f["R"]), p["frame"]["outlier_k"])
            stations[s].update(fitted)
            check_orientations(dev, df.loc[k, CAMPAIGN].to_numpy(), s, p["frame"]["max_orientation_scatter_arcsec"])
    first = next(iter(stations.values()))
    summary = {
        "R": first["R"], "t": first["t"],
        **{k: first[k] for k in ("rms_mm", "n_used")},
        "outliers": outliers,
        "outlier_residual_mm": {p: round(float(v), 4) for p, v in zip(outliers, r[~inl])},
        **{k: first[k] for k in ("mean_mm", "max_mm")},
        "tool_mm": fit["tool_mm"], "method": fit["method"], "condition": fit["condition"],
        **({"tool_held": fit["tool_held"]} if "tool_held" in fit else {}),
        "det_R": float(np.linalg.det(first["R"])),
        **({"tool_rot": first["tool_rot"]} if R_world is not None else {}),
        "stations": stations,
    }
    write_json(root / FRAME_JSON, summary)
    for s, f in stations.items():
        log.info("station %s (%s): fitted base frame (%s) on %d of %d points: rms %.4f mm, mean %.4f mm; "
                 "%d outliers rejected %s", s, ", ".join(f["campaigns"]), fit["method"], f["n_used"], f["n"],
                 f["rms_mm"], f["mean_mm"], len(f["outliers"]), f["outliers"])
    for s, f in stations.items():
        log.info("tool of station %s: %s mm", s, np.round(f["tool_mm"], 3).tolist())
        if "tool_rot" in f:
            log.info("probe rotation in the flange, station %s: %s deg (xyz); orientation scatter about it "
                     "%.0f arcsec mean on %d poses", s, np.round(np.degrees(f["tool_rot"]), 4).tolist(),
                     f["orientation_scatter_arcsec"]["mean"], f["orientation_n_used"])
    for c, why in fit.get("tool_held", {}).items():
        log.warning("tool component %s %s", c, why)
    return summary


main = stage_main(__spec__.name, __doc__, run)         # main(argv=None, root=HERE)

if __name__ == "__main__":
    script(__spec__.name, main)

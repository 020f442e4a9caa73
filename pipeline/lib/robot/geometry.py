"""Which geometry each branch runs on; every input is a value the stage read and passed.

theory_geometry    nominal DH with the frame stage's tool: the theory points and the paper's
                   (nominal) physics branch
Calibration        the calibrate stage's result: the calibrated geometry, and each tracker
                   station's frame correction and tool offset
with_parts         the calibrated geometry with the parts stage's per-joint error maps
physics_geometry   `model.physics`: nominal (the above) or calibrated (with the maps)
aligned            measured points of every tracker station in the first station's base frame
                   (and tool), with the station corrections the calibrate stage identified
"""
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import torch

from pipeline.lib.project.columns import ERR, JOINTS_DEG, MEAS, MEAS_Q, STATION, THEORY
from pipeline.lib.robot.errormaps import MAP_KEYS
from pipeline.lib.robot.frames import measured_rotations, quaternions
from pipeline.lib.robot.kinematics import DTYPE, RIGID_KEYS, TOOL_ROT, fk, nominal_geometry, rigid_xyz
from pipeline.lib.robot.robots import Robot

PHYSICS = ("calibrated", "nominal")


def theory_geometry(robot: Robot, tool_mm, tool_rot=None) -> dict:
    """Nominal DH geometry of `robot` with the tool offset the frame stage settled on (tool_mm) and, where
    the campaign measures orientation, the probe's rotation in the flange (tool_rot, [rx, ry, rz] rad)."""
    g = {**nominal_geometry(robot), "tool": torch.as_tensor(np.asarray(tool_mm, float), dtype=DTYPE)}
    return g if tool_rot is None else {**g, TOOL_ROT: torch.as_tensor(np.asarray(tool_rot, float), dtype=DTYPE)}


@dataclass
class Calibration:
    """models/calibration.json as values: the geometry, and per further station its frame correction
    [rx, ry, rz rad, tx, ty, tz mm] and tool offset minus the first station's (mm)."""
    geometry: dict
    stations: dict = field(default_factory=dict)
    station_tools: dict = field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: dict) -> "Calibration":
        """From the saved JSON (kinematics.save_geometry's layout)."""
        g = {k: torch.tensor(d["geometry"][k], dtype=DTYPE) for k in RIGID_KEYS + MAP_KEYS if k in d["geometry"]}
        return cls(g, d.get("stations", {}), d.get("station_tools", {}))


def with_parts(geometry: dict, parts: dict) -> dict:
    """The parts stage's geometry (models/parts.json: the calibration re-estimated with the per-joint error
    maps in its chain) when the maps hold, else `geometry` (the calibration's)."""
    return Calibration.from_dict(parts).geometry if parts["enabled"] else geometry


def at_temperature(geometry: dict, dT: float, cte_per_k: float) -> dict:
    """geometry with its link lengths (a, d) expanded by cte_per_k·dT: the arm dT kelvin warmer than
    when it was calibrated (a linear expansion coefficient, e.g. 23e-6/K for aluminium links)."""
    s = 1.0 + cte_per_k * dT
    return {**geometry, "a": geometry["a"] * s, "d": geometry["d"] * s}


def physics_geometry(physics: str, calibrated: dict, nominal: dict) -> dict:
    """The physics branch's geometry for `model.physics`: the calibrated one (with the error maps:
    with_parts) or the nominal one."""
    if physics == "calibrated":
        return calibrated
    if physics == "nominal":
        return nominal
    raise ValueError(f"params.yaml model.physics: {physics!r}; use one of {PHYSICS}")


def aligned(df: pd.DataFrame, calibration: Calibration, nominal: dict) -> pd.DataFrame:
    """df (points table) with every station's points as if measured from the first station with
    the first station's tool, where the model lives (one station, one tool: df unchanged).

    meas = R^T (meas_station - t) - R_base R_flange(q) dtool, with the station's correction (R, t)
    and tool offset dtool identified by calibrate (R_flange of the calibrated geometry);
    theory = nominal DH (`nominal`: theory_geometry) with the first station's tool; err = meas - theory.
    """
    g = calibration.geometry
    out = df.copy()
    for s, d in calibration.stations.items():
        m = (df[STATION] == s).to_numpy()
        dtool = np.asarray(calibration.station_tools.get(s, [0.0, 0.0, 0.0]), float)
        if not m.any() or not (any(d) or dtool.any()):
            continue
        R, t = (v.numpy() for v in rigid_xyz(torch.tensor(d, dtype=DTYPE)))
        meas = (df.loc[m, MEAS].to_numpy() - t) @ R
        if dtool.any():                                # the marker's offset from the first tool, moved by the arm
            q = torch.as_tensor(np.radians(df.loc[m, JOINTS_DEG].to_numpy()), dtype=DTYPE)
            with torch.no_grad():
                meas -= (fk(q, {**g, "tool": g["tool"] + torch.as_tensor(dtool, dtype=DTYPE)}) - fk(q, g)).numpy()
                out.loc[m, THEORY] = fk(q, nominal).numpy()
        out.loc[m, MEAS] = meas
        out.loc[m, ERR] = meas - out.loc[m, THEORY].to_numpy()
        if set(MEAS_Q) <= set(df.columns):             # orientations too: R^T R_station
            out.loc[m, MEAS_Q] = quaternions(np.einsum("ji,njk->nik", R, measured_rotations(df.loc[m])))
    return out

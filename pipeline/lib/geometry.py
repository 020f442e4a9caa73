"""Which geometry each branch runs on, read from the stage outputs.

theory_geometry    nominal DH with the frame stage's tool: the theory points and the paper's
                   (nominal) physics branch
physics_geometry   `model.physics`: nominal (the above) or calibrated (the calibrate stage's)
aligned            measured points of every tracker station in the first station's base frame
                   (and tool), with the station corrections the calibrate stage identified
"""
import numpy as np
import pandas as pd
import torch

from .artifacts import CALIBRATED_GEOMETRY, FRAME_JSON
from .columns import ERR, JOINTS_DEG, MEAS, STATION, THEORY
from .config import read_json
from .kinematics import DTYPE, fk, load_geometry, nominal_geometry, rigid_xyz
from .robots import load_robot


def theory_geometry(params: dict) -> tuple:
    """(robot, nominal DH geometry) with the tool offset the frame stage settled on."""
    robot = load_robot(params["robot"])
    robot.tool = np.asarray(read_json(FRAME_JSON)["tool_mm"], float)
    return robot, nominal_geometry(robot)


def physics_geometry(params: dict, physics: str) -> dict:
    """The physics branch's geometry: `nominal` (theory_geometry) or `calibrated` (calibrate stage)."""
    if physics == "calibrated":
        return load_geometry(CALIBRATED_GEOMETRY)
    if physics == "nominal":
        return theory_geometry(params)[1]
    raise ValueError(f"params.yaml model.physics: {physics!r}; use nominal or calibrated")


def aligned(df: pd.DataFrame, params: dict, cal: dict | None = None) -> pd.DataFrame:
    """df (points table) with every station's points as if measured from the first station with
    the first station's tool, where the model lives (one station, one tool: df unchanged).

    meas = R^T (meas_station - t) - R_base R_flange(q) dtool, with the station's correction (R, t)
    and tool offset dtool identified by calibrate (R_flange of the calibrated geometry);
    theory = nominal DH with the first station's tool; err = meas - theory.
    cal: {"stations", "station_tools", "geometry"}; default models/calibration.json.
    """
    if cal is None:
        cal = {**read_json(CALIBRATED_GEOMETRY), "geometry": load_geometry(CALIBRATED_GEOMETRY)}
    tools = cal.get("station_tools", {})
    g, g_nom = cal.get("geometry"), None
    out = df.copy()
    for s, d in cal.get("stations", {}).items():
        m = (df[STATION] == s).to_numpy()
        dtool = np.asarray(tools.get(s, [0.0, 0.0, 0.0]), float)
        if not m.any() or not (any(d) or dtool.any()):
            continue
        R, t = (v.numpy() for v in rigid_xyz(torch.tensor(d, dtype=DTYPE)))
        meas = (df.loc[m, MEAS].to_numpy() - t) @ R
        if dtool.any():                                # the marker's offset from the first tool, moved by the arm
            q = torch.as_tensor(np.radians(df.loc[m, JOINTS_DEG].to_numpy()), dtype=DTYPE)
            g_nom = g_nom or theory_geometry(params)[1]
            with torch.no_grad():
                meas -= (fk(q, {**g, "tool": g["tool"] + torch.as_tensor(dtool, dtype=DTYPE)}) - fk(q, g)).numpy()
                out.loc[m, THEORY] = fk(q, g_nom).numpy()
        out.loc[m, MEAS] = meas
        out.loc[m, ERR] = meas - out.loc[m, THEORY].to_numpy()
    return out

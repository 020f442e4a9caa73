"""Which geometry each branch runs on, read from the stage outputs.

theory_geometry    nominal DH with the frame stage's tool: the theory points and the paper's
                   (nominal) physics branch
physics_geometry   `model.physics`: nominal (the above) or calibrated (the calibrate stage's)
aligned            measured points of every tracker station in the first station's base frame,
                   with the station corrections the calibrate stage identified
"""
import numpy as np
import pandas as pd
import torch

from .artifacts import CALIBRATED_GEOMETRY, FRAME_JSON
from .columns import ERR, MEAS, STATION, THEORY
from .config import read_json
from .kinematics import DTYPE, load_geometry, nominal_geometry, rigid_xyz
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


def aligned(df: pd.DataFrame, corrections: dict | None = None) -> pd.DataFrame:
    """df (points table) with meas (and err) of each station mapped into the first station's base
    frame: p = R^T (p_station - t), (R, t) the station's correction (default: models/calibration.json's
    "stations"; the first station's is zero). One station: df unchanged."""
    if corrections is None:
        corrections = read_json(CALIBRATED_GEOMETRY).get("stations", {})
    out = df.copy()
    for s, d in corrections.items():
        m = (df[STATION] == s).to_numpy()
        if not any(d) or not m.any():
            continue
        R, t = (v.numpy() for v in rigid_xyz(torch.tensor(d, dtype=DTYPE)))
        out.loc[m, MEAS] = (df.loc[m, MEAS].to_numpy() - t) @ R
        out.loc[m, ERR] = out.loc[m, MEAS].to_numpy() - df.loc[m, THEORY].to_numpy()
    return out

"""Which geometry each branch runs on, read from the stage outputs.

theory_geometry    nominal DH with the frame stage's tool: the theory points and the paper's
                   (nominal) physics branch
physics_geometry   `model.physics`: nominal (the above) or calibrated (the calibrate stage's)
"""
import numpy as np

from .artifacts import CALIBRATED_GEOMETRY, FRAME_JSON
from .config import read_json
from .kinematics import load_geometry, nominal_geometry
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

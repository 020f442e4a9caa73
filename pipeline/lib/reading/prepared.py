"""What every learning stage starts from, read back once: the theory points with their split, aligned by
the calibration's base frame and tool (geometry.aligned), the robot, the nominal and calibrated geometries,
and the per-joint error maps. The outputs of frame, theory, split, calibrate and parts (lib/project/artifacts.py);
train, baselines, evaluate, compensate, ablation, the benchmarks and the tests read them here."""
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from pipeline.lib.project.artifacts import CALIBRATED_GEOMETRY, FRAME_JSON, HERE, PARTS_JSON, load_points
from pipeline.lib.project.config import read_json
from pipeline.lib.robot.geometry import Calibration, aligned, theory_geometry, with_parts
from pipeline.lib.robot.robots import Robot, load_robot


@dataclass(frozen=True)
class Prepared:
    points: pd.DataFrame         # aligned points, with their split
    robot: Robot
    frame: dict                  # reports/frame.json
    nominal: dict                # the nominal geometry with the frame's tool
    calibration: Calibration
    parts: dict | None           # models/parts.json; None when not read

    @property
    def calibrated(self) -> dict:
        """The calibrated geometry with its per-joint error maps."""
        return with_parts(self.calibration.geometry, self.parts)

    def geometries(self) -> dict:
        """The physics branches a model can sit on: {"calibrated" (with the error maps), "nominal"}."""
        return {"calibrated": self.calibrated, "nominal": self.nominal}


def load_prepared(robot_params: dict, root: Path = HERE, parts: bool = True) -> Prepared:
    """The prepared inputs of the project at `root` (parts: read the error maps too)."""
    robot, frame = load_robot(robot_params), read_json(root / FRAME_JSON)
    nominal = theory_geometry(robot, frame["tool_mm"])
    calibration = Calibration.from_dict(read_json(root / CALIBRATED_GEOMETRY))
    return Prepared(aligned(load_points(root), calibration, nominal), robot, frame, nominal, calibration,
                    read_json(root / PARTS_JSON) if parts else None)

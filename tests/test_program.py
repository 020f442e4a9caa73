"""The program compensator: a program's waypoints in, a compensated CSV and URScript out."""
import re

import numpy as np
import pandas as pd
import pytest
import torch

from pipeline import program
from pipeline.lib.artifacts import load_points
from pipeline.lib.columns import JCOMP_DEG, JOINTS_DEG, TARGET, THEORY
from pipeline.lib.kinematics import DTYPE
from pipeline.lib.training import load_model


def model_at(params, q_deg):
    with torch.no_grad():
        return load_model(params)(torch.as_tensor(np.radians(q_deg), dtype=DTYPE))[0].numpy()


def test_offline_waypoints_land_where_the_nominal_program_meant(in_trained_project, tmp_path):
    """Joint targets only: target = nominal position (for the test points, their theory column);
    the model at the compensated joints is there within tol_mm, and the URScript carries those joints."""
    params = in_trained_project
    pts = load_points().query("split == 'test'").head(12)
    src = tmp_path / "prog.csv"
    pts[JOINTS_DEG].to_csv(src, index=False)
    table = program.main([str(src)])
    np.testing.assert_allclose(table[TARGET].to_numpy(), pts[THEORY].to_numpy(), atol=1e-9)
    assert table["converged"].all() and table.point_id.tolist()[:2] == ["W001", "W002"]
    tol = params["compensate"]["tol_mm"]
    assert np.linalg.norm(model_at(params, table[JCOMP_DEG].to_numpy()) - pts[THEORY].to_numpy(), axis=1).max() < tol
    assert (np.abs(table[JCOMP_DEG].to_numpy() - pts[JOINTS_DEG].to_numpy()) > 1e-4).any()   # it did move them
    back = pd.read_csv(tmp_path / "prog_comp.csv")
    assert list(back.columns[:7]) == ["point_id"] + JOINTS_DEG and len(back) == 12
    script = (tmp_path / "prog_comp.script").read_text()
    moves = re.findall(r"movej\(\[([^\]]+)\], a=acc, v=vel\)", script)
    assert len(moves) == 12 and script.startswith("# compensated") and script.rstrip().endswith("end")
    q_script = np.array([[float(v) for v in m.split(",")] for m in moves])
    np.testing.assert_allclose(q_script, np.radians(table[JCOMP_DEG].to_numpy()), atol=1e-8)


def test_positions_with_starting_joints(in_trained_project, tmp_path):
    params = in_trained_project
    pts = load_points().query("split == 'test'").head(5)
    target = pts[THEORY].to_numpy() + [0.5, -0.3, 0.2]                  # half a millimetre elsewhere
    src = tmp_path / "pos.csv"
    pts[JOINTS_DEG].assign(point_id=pts.point_id.to_numpy(), **dict(zip(TARGET, target.T))).to_csv(src, index=False)
    table = program.main([str(src), "--out", str(tmp_path / "o.csv"), "--urscript", str(tmp_path / "o.script")])
    assert table.point_id.tolist() == pts.point_id.tolist()
    assert np.linalg.norm(model_at(params, table[JCOMP_DEG].to_numpy()) - target, axis=1).max() < \
        params["compensate"]["tol_mm"]
    assert (tmp_path / "o.script").read_text().count("movej(") == 5


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.drop(columns="j4_deg"), r"missing column\(s\) \['j4_deg'\]"),
    (lambda d: d.assign(j3_deg=["1.0", "x", "2", "3"]), r"row 3, column j3_deg: not a finite number \('x'\)"),
    (lambda d: d.assign(j2_deg=[0.0, 0.0, 0.0, 400.0]), r"row 5, column j2_deg: 400.0° beyond the joint limits"),
    (lambda d: d.assign(target_x=1.0, target_y=2.0), r"target columns need all of"),
])
def test_bad_waypoints_are_named_by_file_row_and_column(in_trained_project, tmp_path, edit, message):
    src = tmp_path / "bad.csv"
    edit(pd.DataFrame(np.zeros((4, 6)), columns=JOINTS_DEG)).to_csv(src, index=False)
    with pytest.raises(ValueError, match=message) as e:
        program.main([str(src)])
    assert str(src) in str(e.value)

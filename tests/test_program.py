"""The program compensator: a program's waypoints in, a compensated CSV and URScript out."""
import os
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from conftest import exit_code, served_model
from pipeline.commands import path as path_command, plan, program
from pipeline.lib.project.artifacts import load_points
from pipeline.lib.project import writing
from pipeline.lib.project.columns import DJ_DEG, JCOMP_DEG, JOINTS_DEG, TARGET, THEORY
from pipeline.lib.robot.kinematics import DTYPE, fk_numpy
from pipeline.lib.robot.robots import load_robot, nominal_robot
from pipeline.lib.runtime.waypoints import read_waypoints


def model_at(params, q_deg):
    with torch.no_grad():
        return served_model()(torch.as_tensor(np.radians(q_deg), dtype=DTYPE))[0].numpy()


def test_offline_waypoints_land_where_the_nominal_program_meant(in_trained_project, tmp_path):
    """Joint targets only: target = nominal position (for the test points, their theory column);
    the model at the compensated joints is there within tol_mm, and the URScript carries those joints."""
    params = in_trained_project
    pts = load_points().query("split == 'test'").head(12)
    src = tmp_path / "prog.csv"
    pts[JOINTS_DEG].to_csv(src, index=False)
    table = program.run([str(src)])
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
    table = program.run([str(src), "--out", str(tmp_path / "o.csv"), "--urscript", str(tmp_path / "o.script")])
    assert table.point_id.tolist() == pts.point_id.tolist()
    assert np.linalg.norm(model_at(params, table[JCOMP_DEG].to_numpy()) - target, axis=1).max() < \
        params["compensate"]["tol_mm"]
    assert (tmp_path / "o.script").read_text().count("movej(") == 5


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.drop(columns="j4_deg"), r"column 'j4_deg': missing waypoint column 'j4_deg'"),
    (lambda d: d.assign(j3_deg=["1.0", "x", "2", "3"]), r"row 3, column 'j3_deg': not a finite number"),
    (lambda d: d.assign(j2_deg=[0.0, 0.0, 0.0, 400.0]), r"row 5, column 'j2_deg': 400.0° beyond the joint limits"),
    (lambda d: d.assign(target_x=1.0, target_y=2.0), r"target columns need all of"),
    (lambda d: d.assign(j5_deg=["1e999", "1", "2", "3"]), r"row 2, column 'j5_deg': not a finite number"),
    (lambda d: d.assign(target_x=-400.0, target_y=-100.0, target_z=300.0, target_rx=[0.0, 0.0, 1e300, 0.0],
                        target_ry=0.0, target_rz=0.0),                 # was NaN inside, then a traceback
     r"row 4, column 'target_rx': a rotation vector inf rad long, more than π"),
    (lambda d: d.assign(target_x=-400.0, target_y=-100.0, target_z=300.0, target_rx=[0.0, 180.0, 0.0, 0.0],
                        target_ry=0.0, target_rz=0.0), r"row 3, column 'target_rx': a rotation vector 180 rad long"),
])
def test_bad_waypoints_are_named_by_file_row_and_column(in_trained_project, tmp_path, edit, message):
    src = tmp_path / "bad.csv"
    edit(pd.DataFrame(np.zeros((4, 6)), columns=JOINTS_DEG)).to_csv(src, index=False)
    with pytest.raises(ValueError, match=message) as e:
        program.run([str(src)])
    assert str(src) in str(e.value)


def program_file(tmp_path, n=6, **columns) -> Path:
    """n test-split waypoints (their recorded joints) as a CSV, with extra or replaced columns."""
    pts = load_points().query("split == 'test'").head(n)
    df = pts[JOINTS_DEG].reset_index(drop=True).assign(**columns)
    src = tmp_path / "prog.csv"
    df.to_csv(src, index=False)
    return src



def test_an_id_cannot_inject_urscript(in_trained_project, tmp_path, capsys):
    """Issue 21, defect 1: a point id with a newline put live lines into the URScript comment. Now every
    id must match ID_PATTERN; the file is refused with its row and column, nothing is written."""
    for bad in ['W2\n  set_digital_out(0, True)\n  popup("x")', 'W2 set_digital_out(0,True)', "W2\tpopup(1)", "x" * 65]:
        ids = [f"W{i}" for i in range(6)]
        ids[2] = bad
        src = program_file(tmp_path, point_id=ids)
        code, said = exit_code(program.main, [str(src)], capsys)
        assert code == 2 and "row 4" in said and "Traceback" not in said, said
        assert not (tmp_path / "prog_comp.script").exists() and not (tmp_path / "prog_comp.csv").exists()
    ok = program_file(tmp_path, point_id=["a:1", "b_2", "c-3", "d.4", "E5", "f6"])   # campaign ids pass
    assert exit_code(program.main, [str(ok)], capsys)[0] == 0
    script = (tmp_path / "prog_comp.script").read_text()
    for line in script.splitlines():                   # every line is ours: a comment, def/end, a number
        assert re.fullmatch(r"(# .*|def compensated_program\(\):|end|  (acc|vel) = [0-9.]+|  # [A-Za-z0-9_.:-]+: "
                            r"[^\n]*|  movej\(\[[-0-9., ]+\], a=acc, v=vel\))", line), line


def test_an_unreached_waypoint_never_becomes_a_move(in_trained_project, tmp_path, capsys):
    """Defect 2: a target 5 m away wrote a movej (residual 4050 mm) and exit 0. Now the program is refused
    (exit 1, the waypoint named, nothing written); with --comment-out-unreached it is a comment, no move."""
    pts = load_points().query("split == 'test'").head(4)
    target = pts[THEORY].to_numpy().copy()
    target[1] = [5000.0, 0.0, 0.0]                                          # beyond the reach: refused at once
    target[2] = [0.0, 0.0, 1.0]                                             # inside the reach, unreachable
    src = tmp_path / "prog.csv"
    pts[JOINTS_DEG].assign(point_id=["A", "B", "C", "D"], **dict(zip(TARGET, target.T))).to_csv(src, index=False)
    code, said = exit_code(program.main, [str(src)], capsys)
    assert code == 1 and "B: target 5000.0 mm from the base, beyond the arm's reach" in said
    assert f"{src}: unreachable: " in said and "; nothing written" in said          # the file named (a review)
    assert not (tmp_path / "prog_comp.script").exists()
    target[1] = pts[THEORY].to_numpy()[1]
    pts[JOINTS_DEG].assign(point_id=["A", "B", "C", "D"], **dict(zip(TARGET, target.T))).to_csv(src, index=False)
    code, said = exit_code(program.main, [str(src)], capsys)
    assert code == 1 and "NOT REACHED C: residual" in said and "nothing written" in said
    assert not (tmp_path / "prog_comp.script").exists() and not (tmp_path / "prog_comp.csv").exists()
    code, said = exit_code(program.main, [str(src), "--comment-out-unreached"], capsys)
    assert code == 0 and "1 not reached" in said
    script = (tmp_path / "prog_comp.script").read_text()
    assert script.count("movej(") == 3 and "  # C: NOT REACHED (residual" in script
    assert not re.search(r"# C:.*\n  movej", script)                         # no move follows it
    table = pd.read_csv(tmp_path / "prog_comp.csv", keep_default_na=False).set_index("point_id")
    assert not table.loc["C", "converged"]
    # a review (2026-12-06): the CSV gave C's answer as "the angles to command", beside the script's comment
    assert table.loc["C", JCOMP_DEG + DJ_DEG].eq("").all() and table.loc["C", "not_reached"].startswith("residual")
    assert (table.loc[["A", "B", "D"], "not_reached"] == "").all() and table.loc["D", JCOMP_DEG].ne("").all()
    written = (tmp_path / "prog_comp.script").read_bytes()          # refused again: that script is not this run's
    code, said = exit_code(program.main, [str(src)], capsys)
    assert code == 1 and "prog_comp.script: an earlier run's, left as they were, not this one's" in said, said
    assert (tmp_path / "prog_comp.script").read_bytes() == written
    target[1] = [5000.0, 0.0, 0.0]                 # beyond the reach, refused before solving: said likewise
    pts[JOINTS_DEG].assign(point_id=["A", "B", "C", "D"], **dict(zip(TARGET, target.T))).to_csv(src, index=False)
    code, said = exit_code(program.main, [str(src), "--comment-out-unreached"], capsys)
    assert code == 1 and "prog_comp.script: an earlier run's, left as they were, not this one's" in said, said


def test_radians_in_degree_columns_are_refused(in_trained_project, tmp_path, capsys):
    pts = load_points().query("split == 'test'").head(5)
    src = tmp_path / "rad.csv"
    np.radians(pts[JOINTS_DEG]).to_csv(src, index=False)
    code, said = exit_code(program.main, [str(src)], capsys)
    assert code == 2 and "look like radians" in said and not (tmp_path / "rad_comp.script").exists()


def test_empty_files_separators_and_outputs_over_the_input(in_trained_project, tmp_path, capsys):
    """Defect 7: an empty or header-only file was a pandas traceback, `;` and decimal commas were refused,
    and --out could overwrite the input."""
    empty, header = tmp_path / "empty.csv", tmp_path / "header.csv"
    empty.write_text("")
    header.write_text(",".join(JOINTS_DEG) + "\n")
    for f, why in ((empty, "the file is empty"), (header, "no data rows below the header")):
        code, said = exit_code(program.main, [str(f)], capsys)
        assert code == 2 and why in said and "Traceback" not in said
    pts = load_points().query("split == 'test'").head(3)
    semi = tmp_path / "semi.csv"
    semi.write_text(";".join(JOINTS_DEG) + "\n" + "\n".join(
        ";".join(f"{v:.6f}".replace(".", ",") for v in row) for row in pts[JOINTS_DEG].to_numpy()) + "\n")
    table = program.run([str(semi)])
    np.testing.assert_allclose(table[JOINTS_DEG].to_numpy(), pts[JOINTS_DEG].to_numpy(), atol=1e-6)
    code, said = exit_code(program.main, [str(semi), "--out", str(semi)], capsys)
    assert code == 2 and "is the input" in said


def test_waypoints_outside_the_workspace_are_in_the_summary(in_trained_project, tmp_path, capsys):
    """A waypoint far from every training pose is listed in the printed summary, not only the log."""
    pts = load_points().query("split == 'test'").head(3)
    q = pts[JOINTS_DEG].to_numpy().copy()
    q[1] = [150.0, -30.0, 40.0, 10.0, -120.0, 0.0]                    # far from the twin's campaign
    src = tmp_path / "far.csv"
    pd.DataFrame(q, columns=JOINTS_DEG).assign(point_id=["P", "FAR", "Q"]).to_csv(src, index=False)
    code, said = exit_code(program.main, [str(src)], capsys)
    assert code == 0 and "outside the trained workspace" in said
    assert re.search(r"  FAR: [0-9.]+ workspace radii from the nearest training pose", said)


# Issue 32: the second hostile probe
ROW_30 = "P0030,-52,25,-65.691726,126.231097,-67.745261,125.018231,179.796810"   # a decimal comma: 8 cells


def test_a_row_with_one_cell_too_many_is_refused_not_shifted(tmp_path):
    """Critical 1: the row was read with its columns shifted (joint 2 at +25° instead of -65.7°) and became
    a move. A waypoint row is judged by ingest's field_count rule: refused with its file and row."""
    src = tmp_path / "prog.csv"
    src.write_text("point_id," + ",".join(JOINTS_DEG) + "\nP0029,-52.1,-65.6,126.2,-67.7,125.0,179.7\n" + ROW_30 + "\n")
    with pytest.raises(ValueError, match=r"prog.csv, row 3: 8 cells but the header has 7"):
        read_waypoints(src, load_robot({"model": "ur5", "dh": None, "joint_limits_deg": None, "tcp": None, "tool_mm": [0, 0, 0]}))


def test_a_waypoint_beyond_its_limits_or_the_reach_is_refused_before_any_solve(tmp_path, monkeypatch):
    """A mutation review: read_waypoints' joint-limit check and compensate_program's reach refusal were tested
    only through a trained project. A j2_deg of 400° names its row and column; a target twice the reach of the
    chain that would solve it is refused naming its id, before anything is solved."""
    from types import SimpleNamespace

    from pipeline.lib.robot.kinematics import nominal_geometry
    from pipeline.lib.runtime.compensation import reach_mm
    from pipeline.lib.runtime import waypoints
    from pipeline.lib.runtime.waypoints import Refused, compensate_program
    robot = load_robot({"model": "ur5", "dh": None, "joint_limits_deg": None, "tcp": None, "tool_mm": [0, 0, 0]})
    src = tmp_path / "prog.csv"
    src.write_text("point_id," + ",".join(JOINTS_DEG) + "\nA,0,-90,90,-90,-90,0\nB,0,400,90,-90,-90,0\n")
    with pytest.raises(ValueError, match=r"prog.csv, row 3, column 'j2_deg': 400.0° beyond the joint limits"):
        read_waypoints(src, robot)
    g = nominal_geometry(robot)
    df = pd.DataFrame({"point_id": ["A", "B"], **{c: [0.0, 0.0] for c in JOINTS_DEG},
                       "target_x": [400.0, 2 * reach_mm(g)], "target_y": [0.0, 0.0], "target_z": [300.0, 0.0]})
    solved = []
    monkeypatch.setattr(waypoints, "solve", lambda *a, **k: solved.append(a))
    model = SimpleNamespace(physics=SimpleNamespace(geometry=lambda: g))   # only its geometry is asked for
    with pytest.raises(Refused, match=rf"unreachable: B: target {2 * reach_mm(g):.1f} mm from the base, beyond "
                                      rf"the arm's reach of {reach_mm(g):.1f} mm$"):
        compensate_program(df, model, None, robot, g, {"orientation": False})
    assert not solved


def test_a_row_with_one_cell_too_many_is_refused_by_program_and_plan(in_trained_project, tmp_path, capsys):
    src = program_file(tmp_path, n=3)
    src.write_text(src.read_text() + ROW_30.split(",", 1)[1] + "\n")          # no id column: 7 cells for 6
    code, said = exit_code(program.main, [str(src)], capsys)
    assert code == 2 and "row 5: 7 cells but the header has 6" in said and "Traceback" not in said, said
    assert not (tmp_path / "prog_comp.script").exists() and not (tmp_path / "prog_comp.csv").exists()
    code, said = exit_code(plan.main, [str(src), "--n", "3", "--out", str(tmp_path / "o")], capsys)
    assert code == 2 and "row 5: 7 cells but the header has 6" in said and not (tmp_path / "o").exists(), said


def test_duplicate_ids_are_refused_naming_both_rows(in_trained_project, tmp_path, capsys):
    """Major 7: two waypoints D1 were accepted; with --comment-out-unreached both were commented out."""
    src = program_file(tmp_path, n=4, point_id=["A", "D1", "B", "D1"])
    code, said = exit_code(program.main, [str(src), "--comment-out-unreached"], capsys)
    assert code == 2 and "row 5, column 'point_id': point id 'D1' already on row 3" in said, said
    assert not (tmp_path / "prog_comp.script").exists()


def test_no_waypoint_reached_says_so_without_nan():
    table = pd.DataFrame({"point_id": ["A", "B"], "residual_mm": [3.0, 4.0], "in_workspace": [True, True]})
    text = program.summary_text(table, {"A": "residual 3 mm", "B": "residual 4 mm"}, None)
    assert text.startswith("2 waypoints: 0 reached, 2 not reached") and "nan" not in text


@pytest.mark.parametrize("link", ["hard", "symbolic"])
def test_an_output_linked_to_the_input_is_refused_and_the_input_kept(tmp_path, capsys, link):
    """Critical 2: `ln in.csv in_hard.csv; program in.csv --out in_hard.csv` replaced the input with the
    Δθ table. Refused before any work (no trained project needed), by inode, for either output."""
    src = tmp_path / "in.csv"
    src.write_text(",".join(JOINTS_DEG) + "\n" + ",".join(["10.0"] * 6) + "\n")
    before = src.read_bytes()
    alias = tmp_path / "alias.csv"
    (os.link if link == "hard" else os.symlink)(src, alias)
    for flag in ("--out", "--urscript"):
        code, said = exit_code(program.main, [str(src), flag, str(alias)], capsys)
        assert code == 2 and "is the input" in said and "Traceback" not in said, said
        assert src.read_bytes() == before
    plan_dir = tmp_path / "plan"
    plan_dir.mkdir()
    (os.link if link == "hard" else os.symlink)(src, plan_dir / "poses.csv")
    code, said = exit_code(plan.main, [str(src), "--n", "3", "--out", str(plan_dir)], capsys)
    assert code == 2 and "is the input" in said and src.read_bytes() == before, said


def test_an_output_in_a_folder_that_does_not_exist_is_refused_before_any_work(tmp_path, capsys):
    """It was refused only after the whole program was solved (the write failed); now before the project is
    even read (no trained project needed), naming the folder."""
    src = tmp_path / "in.csv"
    src.write_text(",".join(JOINTS_DEG) + "\n" + ",".join(["10.0"] * 6) + "\n")
    for flag in ("--out", "--urscript"):
        code, said = exit_code(program.main, [str(src), flag, str(tmp_path / "none" / "x.out"),
                                              "--project", str(tmp_path / "no_project")], capsys)
        assert code == 2 and f"its folder {tmp_path / 'none'} does not exist; nothing written" in said, said
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.csv"]


def test_an_unwritable_urscript_leaves_no_csv(in_trained_project, tmp_path, capsys):
    """Minor: `--urscript` to a bad path wrote the CSV and then failed (exit 2). Both or neither."""
    src = program_file(tmp_path, n=3)
    code, said = exit_code(program.main, [str(src), "--urscript", str(tmp_path / "no" / "such" / "dir.script")], capsys)
    assert code == 2 and "nothing written" in said and "Traceback" not in said, said
    assert not (tmp_path / "prog_comp.csv").exists() and not list(tmp_path.glob(".*tmp"))


def test_a_urscript_path_that_is_a_folder_leaves_the_csv_as_it_was(in_trained_project, tmp_path, capsys):
    """The defect: the CSV was renamed into place, then the URScript's rename failed on a folder (exit 2):
    a new table beside an old program. Now a folder is refused before anything is written."""
    src, out = program_file(tmp_path, n=3), tmp_path / "prog_comp.csv"
    out.write_text("OLD CONTENT\n")
    (tmp_path / "prog.script").mkdir()
    code, said = exit_code(program.main, [str(src), "--out", str(out), "--urscript", str(tmp_path / "prog.script")],
                           capsys)
    assert code == 2 and "prog.script (a folder); nothing written" in said and "Traceback" not in said, said
    assert out.read_text() == "OLD CONTENT\n" and not list(tmp_path.glob(".*tmp*"))


def test_a_failed_rename_puts_back_the_files_renamed_before_it(tmp_path, monkeypatch):
    """write_together: should the second rename fail (here made to), the first file is the one it replaced
    again, the third never written, and no temporary file is left."""
    a, b, c = tmp_path / "a.csv", tmp_path / "b.script", tmp_path / "c.txt"
    a.write_text("old a")
    real = os.replace

    def failing(src, dst):
        if Path(dst) == b:
            raise OSError(28, "No space left on device")
        real(src, dst)
    monkeypatch.setattr(writing.os, "replace", failing)
    with pytest.raises(OSError, match=r"cannot write .*b.script \(No space left on device\); nothing written"):
        writing.write_together({a: "new a", b: "new b", c: "new c"})
    assert a.read_text() == "old a" and not b.exists() and not c.exists()
    assert sorted(f.name for f in tmp_path.iterdir()) == ["a.csv"]


def test_a_failed_write_names_its_file(tmp_path, monkeypatch):
    """The defect: a disk full while writing the second file said only "[Errno 28] No space left on device"."""
    a, b = tmp_path / "a.csv", tmp_path / "b.script"
    real, calls = writing.os.fsync, []

    def full(fd):
        calls.append(fd)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        real(fd)
    monkeypatch.setattr(writing.os, "fsync", full)
    with pytest.raises(OSError, match=r"cannot write .*b.script \(No space left on device\); nothing written"):
        writing.write_together({a: "new a", b: "new b"})
    assert sorted(f.name for f in tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", ["target_x_mm", "tx", "Target X", "target_rz_rad",
                                  "target.x", "x_mm", "Z [mm]", "pos_x", "target_x\u200b", "targetｘ"])   # a review
def test_a_misnamed_column_is_refused_not_left_unread(in_trained_project, tmp_path, name):
    """The defect: target_x_mm, target_y_mm, target_z_mm were not read: the waypoints were solved as offline
    ones, for other positions (50 mm off in the review's file), exit 0. A column the reader does not use and
    whose name looks like one it would is now refused, naming it; any other is logged as not used."""
    src = program_file(tmp_path, **{name: 1.0})                # (2026-12-06: the last six were logged, not used)
    with pytest.raises(ValueError, match=rf"prog.csv, column '{re.escape(name)}': a column this reader does not know"):
        read_waypoints(src, nominal_robot("ur5"))


def test_a_column_the_reader_does_not_use_is_said(in_trained_project, tmp_path, caplog):
    """Not refused: what a UR log carries beside actual_q_* (target_q_*, actual_qd_*), another joint set, labels,
    the program's own output columns (a review of the first version refused these)."""
    extra = {"speed": 0.5, "move": "movej", "target_q_0": 1.0, "actual_qd_0": 0.0, "j1_rad": 0.1, "point_name": "a",
             "target": "weld", "joint_speed": 1.0, "j1_comp_deg": 1.0}
    src = program_file(tmp_path, **extra)
    with caplog.at_level("WARNING"):
        read_waypoints(src, nominal_robot("ur5"))
    assert "prog.csv: column(s) not used: " + ", ".join(extra) in caplog.text


def test_an_output_over_a_project_file_is_refused(in_trained_project, tmp_path, capsys):
    """The defect: `--urscript reports/frame.json` replaced the project's frame with URScript (only the
    waypoints file counted as an input)."""
    src = program_file(tmp_path)
    frame = Path("reports/frame.json").read_bytes()
    code, said = exit_code(program.main, [str(src), "--urscript", "reports/frame.json"], capsys)
    assert code == 2 and "reports/frame.json is the input reports/frame.json" in said, said
    assert Path("reports/frame.json").read_bytes() == frame


@pytest.mark.parametrize("flag, target", [("--out", "reports/compensation.csv"), ("--urscript", "reports/bench/x.script"),
                                          ("--out", "reports/plots/a.csv"), ("--out", "dvc.lock")])
def test_an_output_over_a_pipeline_output_or_record_is_refused(in_trained_project, tmp_path, capsys, flag, target):
    """The defect (a review): `--out reports/compensation.csv` replaced the compensate stage's Δθ table, exit 0
    (only the files a command reads were guarded; `dvc repro` would serve the stale table as its own). Every
    output dvc.lock records (a folder's files too), the settings and the benchmark records are refused now."""
    src = program_file(tmp_path)
    before = Path(target).read_bytes() if Path(target).is_file() else None
    code, said = exit_code(program.main, [str(src), flag, target], capsys)
    assert code == 2 and f"{target} is the project's own" in said, said
    assert (Path(target).read_bytes() if Path(target).is_file() else None) == before


def test_the_script_is_ascii(in_trained_project, tmp_path, capsys):
    """The defect: "rad/s²" in the header and "°" in a not-reached comment: a controller's reader need not
    take UTF-8. Both ASCII now."""
    pts = load_points().query("split == 'test'").head(3)
    target = pts[THEORY].to_numpy().copy()
    target[1] = [0.0, 0.0, 1.0]                                             # unreachable: a comment
    src = tmp_path / "prog.csv"
    pts[JOINTS_DEG].assign(point_id=["A", "B", "C"], **dict(zip(TARGET, target.T))).to_csv(src, index=False)
    assert exit_code(program.main, [str(src), "--comment-out-unreached"], capsys)[0] == 0
    script = (tmp_path / "prog_comp.script").read_text()
    assert script.isascii() and "rad/s^2" in script


def test_the_planner_refuses_a_target_the_arm_cannot_reach(in_trained_project, tmp_path, capsys):
    """Minor: a program target the calibrated arm could not reach was planned silently ("50% -> 50%")."""
    pts = load_points().query("split == 'test'").head(2)
    target = pts[THEORY].to_numpy().copy()
    target[1] = [0.0, 0.0, 1.0]                                        # inside the reach bound, unreachable
    src = tmp_path / "prog.csv"
    pts[JOINTS_DEG].assign(point_id=["A", "B"], **dict(zip(TARGET, target.T))).to_csv(src, index=False)
    code, said = exit_code(plan.main, [str(src), "--n", "3", "--out", str(tmp_path / "o")], capsys)
    assert code == 1 and re.search(r"B: \d+\.\d mm short", said) and "A:" not in said, said
    assert not (tmp_path / "o" / "poses.csv").exists()


def test_radian_columns_are_read_as_radians(tmp_path):
    """Issue 33: the program took degrees only, where ingest reads j*_rad and UR's actual_q_*."""
    robot = load_robot({"model": "ur5", "dh": None, "joint_limits_deg": None, "tcp": None, "tool_mm": [0, 0, 0]})
    q = np.array([[13.5, -54.6, 121.7, 85.0, 148.9, 55.6], [-29.9, -84.9, 105.6, -209.9, 114.0, -48.9]])
    for names in ([f"j{i}_rad" for i in range(1, 7)], [f"actual_q_{i}" for i in range(6)]):
        src = tmp_path / "rad.csv"
        pd.DataFrame(np.radians(q), columns=names).to_csv(src, index=False)
        np.testing.assert_allclose(read_waypoints(src, robot)[JOINTS_DEG].to_numpy(), q, atol=1e-9)
    src.write_text("j1_deg,j2_deg\n1,2\n")
    with pytest.raises(ValueError, match=r"column 'j3_deg': missing waypoint column 'j3_deg' \(or j1_rad"):
        read_waypoints(src, robot)


def test_the_move_and_its_speeds_are_settings(in_trained_project, tmp_path, capsys, monkeypatch):
    """Issue 33: every move was a movej with acceleration and speed written into the code. (Three test poses in
    one configuration: a movel between two in different ones is refused, below.)"""
    from pipeline.lib.robot.poses import configuration_margin
    pts = load_points().query("split == 'test'")
    side = np.sign(configuration_margin(pts[JOINTS_DEG].to_numpy(), served_model().physics.geometry()))
    same = pts[(side == side[0]).all(1)].head(3)
    src = tmp_path / "prog.csv"
    same[JOINTS_DEG].to_csv(src, index=False)
    p = in_trained_project
    p["program"] = {"move": "movel", "movej": {"acc": 1.4, "vel": 1.05}, "movel": {"acc": 0.5, "vel": 0.1}}
    monkeypatch.setattr(program, "load_params", lambda path: p)
    assert exit_code(program.main, [str(src)], capsys)[0] == 0
    script = (tmp_path / "prog_comp.script").read_text()
    assert script.count("  movel([") == 3 and "movej" not in script.split("\n", 1)[1]
    assert "  acc = 0.500000" in script and "  vel = 0.100000" in script and "m/s^2, m/s" in script


def test_a_movej_faster_than_the_robots_slowest_joint_is_refused_before_any_work(in_trained_project, tmp_path,
                                                                                capsys, monkeypatch):
    """A speed under the generic cap (2π rad/s) but above this robot's joints (a UR5's 180 deg/s: π rad/s) went
    into the script as written; the program compensator and the planner and the path command (its approach) now refuse it, naming the key."""
    src = program_file(tmp_path, n=3)
    p = in_trained_project
    assert p["robot"]["model"] == "ur5"
    p["program"] = {**p["program"], "move": "movej", "movej": {"acc": 1.4, "vel": 3.2}}
    p["plan"] = {**p["plan"], "vel": 3.2}
    monkeypatch.setattr(program, "load_params", lambda path: p)
    monkeypatch.setattr(plan, "load_params", lambda path: p)
    monkeypatch.setattr(path_command, "load_params", lambda path: p)
    code, said = exit_code(program.main, [str(src)], capsys)
    assert code != 0 and "program.movej.vel: 3.2 rad/s, faster than the ur5's slowest joint (3.142 rad/s" in said, said
    assert not (tmp_path / "prog_comp.script").exists()
    code, said = exit_code(plan.main, [str(src), "--n", "5", "--out", str(tmp_path / "plan")], capsys)
    assert code != 0 and "plan.vel: 3.2 rad/s, faster than the ur5's slowest joint" in said, said
    assert not (tmp_path / "plan").exists()
    code, said = exit_code(path_command.main, [str(src), "--out", str(tmp_path / "path")], capsys)
    assert code != 0 and "program.movej.vel: 3.2 rad/s" in said, said                # the path's approach movej
    assert not (tmp_path / "path").exists()
    p["program"]["movej"]["vel"] = 3.14                                # at the joint's speed: written
    assert exit_code(program.main, [str(src)], capsys)[0] == 0
    assert "  vel = 3.140000" in (tmp_path / "prog_comp.script").read_text()


def test_a_movel_program_through_a_singularity_is_refused(in_trained_project, tmp_path, capsys, monkeypatch):
    """A review (2026-12-06): `program.move: movel` wrote the README's example as 10 movel lines, 5 of whose moves
    put the wrist on the other side of its singularity: a straight line between them passes through it. Now
    refused, naming each such move, nothing written; movej writes it."""
    from pipeline.lib.robot.poses import configuration_margin
    p = in_trained_project
    p["program"] = {**p["program"], "move": "movel"}
    monkeypatch.setattr(program, "load_params", lambda path: p)
    out = [str(tmp_path / "c.csv"), "--urscript", str(tmp_path / "c.script")]
    code, said = exit_code(program.main, ["data/examples/waypoints.csv", "--out", *out], capsys)
    comp = pd.read_csv("data/examples/waypoints.csv")                           # its own joints: where the flips are
    wrist = configuration_margin(comp[JOINTS_DEG].to_numpy(), served_model().physics.geometry())[:, 2]
    expected = int((wrist[:-1] * wrist[1:] < 0).sum())
    assert code != 0 and expected >= 1 and f"{expected} move(s) would take the arm through a singularity" in said, said
    assert "WP01 -> WP02: the wrist on the other side of its singularity" in said and not (tmp_path / "c.script").exists()
    p["program"]["move"] = "movej"
    assert exit_code(program.main, ["data/examples/waypoints.csv", "--out", *out], capsys)[0] == 0


def test_the_example_program_in_the_readme_runs(in_trained_project, tmp_path, capsys):
    example = Path("data/examples/waypoints.csv")
    code, said = exit_code(program.main, [str(example), "--out", str(tmp_path / "c.csv"),
                                          "--urscript", str(tmp_path / "c.script")], capsys)
    assert code == 0 and said.startswith("10 waypoints: 10 reached"), said
    assert (tmp_path / "c.script").read_text().count("movej(") == 10


def test_a_program_compensated_at_a_tcp_lands_the_tcp_on_the_twin(in_trained_project, tmp_path, capsys):
    """--tcp: the waypoints' nominal TCP positions solved for through the probe's pose (issue 34); the twin,
    driven there (noise-free), puts that TCP (fixed to its probe) within a tenth of a millimetre, where the
    uncompensated program misses by about a millimetre."""
    from pipeline.lib.project.config import read_json
    from pipeline.lib.robot.frames import to_base
    from pipeline.lib.robot.tcp import probe_offsets
    from pipeline.lib.sim.twin import Twin
    params = in_trained_project
    pts = load_points().query("split == 'test'").head(20)
    src = tmp_path / "prog.csv"
    pts[JOINTS_DEG].to_csv(src, index=False)
    table = program.run([str(src), "--tcp", "x150"])
    assert table["converged"].all()
    twin, frame = Twin.from_json(params["compensate"]["twin"]), read_json("reports/frame.json")
    o = probe_offsets(params["robot"]["tcp"], served_model().physics.geometry())["x150"]

    def tcp_on_twin(q_deg):
        p, R = twin.expected_pose(q_deg)
        return to_base(twin.to_tracker(p + R @ o), frame)
    after = np.linalg.norm(tcp_on_twin(table[JCOMP_DEG].to_numpy()) - table[TARGET].to_numpy(), axis=1)
    before = np.linalg.norm(tcp_on_twin(pts[JOINTS_DEG].to_numpy()) - table[TARGET].to_numpy(), axis=1)
    assert before.mean() > 0.5 and after.mean() < 0.1 and after.max() < 0.3, (before.mean(), after)
    code, said = exit_code(program.main, [str(src), "--tcp", "nozzle", "--out", str(tmp_path / "x.csv")], capsys)
    assert code == 2 and "--tcp nozzle: not in params.yaml robot.tcp (x150)" in said
    assert not (tmp_path / "x.csv").exists()


def test_offline_waypoints_reach_their_nominal_orientation_on_the_twin(in_trained_project, tmp_path):
    """Issue 34: an offline-programmed waypoint's target is its nominal pose, the flange's orientation too
    (six equations). Driven on the twin (noise-free), the flange turns to within the model's orientation
    accuracy of it (~50″), where the uncompensated program and a position-only solve leave it ~1000″ off;
    the TCP 150 mm off the flange axis lands within a tenth of a millimetre either way."""
    from scipy.spatial.transform import Rotation
    from pipeline.lib.runtime.compensation import nominal_flange, solve
    from pipeline.lib.project.config import read_json
    from pipeline.lib.robot.frames import to_base
    from pipeline.lib.robot.geometry import theory_geometry
    from pipeline.lib.robot.kinematics import fk_numpy, tool_rotation
    from pipeline.lib.robot.tcp import probe_offsets
    from pipeline.lib.sim.twin import Twin
    params = in_trained_project
    pts = load_points().query("split == 'test'").head(20)
    src = tmp_path / "prog.csv"
    pts[JOINTS_DEG].to_csv(src, index=False)
    table = program.run([str(src), "--tcp", "x150"])
    assert table["converged"].all() and table.orientation_residual_arcsec.max() < params["compensate"]["tol_arcsec"]
    assert "orientation 0." in (tmp_path / "prog_comp.script").read_text()
    robot, frame = load_robot(params["robot"]), read_json("reports/frame.json")
    twin, g = Twin.from_json(params["compensate"]["twin"]), served_model().physics.geometry()
    o, tool_rot = probe_offsets(params["robot"]["tcp"], g)["x150"], tool_rotation(g).numpy()
    q0 = pts[JOINTS_DEG].to_numpy()
    goal = nominal_flange(q0, theory_geometry(robot, frame["tool_mm"]))
    tcp_goal = fk_numpy(q0, robot, theory_geometry(robot, params["robot"]["tcp"]["x150"]["xyz_mm"]))

    def on_twin(q_deg):                                      # (TCP error mm, flange orientation error arcsec)
        p, R = twin.expected_pose(q_deg)
        R_base = np.asarray(frame["R"]).T @ twin.R @ R
        turned = Rotation.from_matrix(R_base @ tool_rot.T @ goal.transpose(0, 2, 1)).magnitude()
        return (np.linalg.norm(to_base(twin.to_tracker(p + R @ o), frame) - tcp_goal, axis=1),
                np.degrees(turned) * 3600)
    tcp_after, turned_after = on_twin(table[JCOMP_DEG].to_numpy())
    _, turned_before = on_twin(q0)
    from pipeline.lib.robot.tcp import AtTcp
    position_only = solve(AtTcp(served_model(), o), q0, tcp_goal, params["compensate"], robot, history=False)
    tcp_pos, turned_pos = on_twin(position_only.q_deg)
    assert tcp_after.mean() < 0.1 and tcp_pos.mean() < 0.1
    assert turned_after.mean() < 100 and turned_before.mean() > 500 and turned_pos.mean() > 500, \
        (turned_after.mean(), turned_before.mean(), turned_pos.mean())


def test_a_waypoint_given_an_orientation_reaches_it(in_trained_project, tmp_path, capsys):
    """target_rx..rz (a rotation vector, rad, base frame) with target_x..z: the TCP's frame is turned there.
    Given the nominal pose of each waypoint, the answer is the offline program's; given that pose turned
    0.05° about the base's z axis, the model's flange ends turned with it (scipy, within 1″). Columns without
    a position, or only two of three, are refused naming them."""
    from scipy.spatial.transform import Rotation
    from pipeline.lib.runtime.compensation import nominal_flange
    from pipeline.lib.project.config import read_json
    from pipeline.lib.robot.geometry import theory_geometry
    from pipeline.lib.robot.kinematics import flange_rotations
    params = in_trained_project
    robot, frame = load_robot(params["robot"]), read_json("reports/frame.json")
    pts = load_points().query("split == 'test'").head(8)
    q0 = pts[JOINTS_DEG].to_numpy()
    offline = tmp_path / "offline.csv"
    pts[JOINTS_DEG].to_csv(offline, index=False)
    reference = program.run([str(offline), "--tcp", "x150"])
    flange = nominal_flange(q0, theory_geometry(robot, frame["tool_mm"]))             # the TCP x150 is not turned
    turn = Rotation.from_euler("z", 0.05, degrees=True).as_matrix()
    for name, R in (("same", flange), ("turned", turn @ flange)):
        src = tmp_path / f"{name}.csv"
        rotvec = Rotation.from_matrix(R).as_rotvec()
        pts[JOINTS_DEG].assign(**dict(zip(TARGET, reference[TARGET].to_numpy().T)),
                               **dict(zip(["target_rx", "target_ry", "target_rz"], rotvec.T))).to_csv(src, index=False)
        table = program.run([str(src), "--tcp", "x150"])
        assert table.converged.all() and table.orientation_residual_arcsec.max() < 1.0
        with torch.no_grad():
            got = flange_rotations(torch.as_tensor(np.radians(table[JCOMP_DEG].to_numpy())),
                                   served_model().physics.geometry()).numpy()
        off = np.degrees(Rotation.from_matrix(got @ R.transpose(0, 2, 1)).magnitude()) * 3600
        assert off.max() < 1.0, off
        if name == "same":
            np.testing.assert_allclose(table[JCOMP_DEG].to_numpy(), reference[JCOMP_DEG].to_numpy(), atol=1e-4)
        else:
            assert np.abs(table[JCOMP_DEG].to_numpy() - reference[JCOMP_DEG].to_numpy()).max() > 0.01
    for cols, said in (({"target_rx": 0.0, "target_ry": 0.0, "target_rz": 0.0}, "and a position"),
                       ({"target_x": 1.0, "target_y": 1.0, "target_z": 1.0, "target_rx": 0.0}, "needs all of")):
        src = tmp_path / "bad.csv"
        pts[JOINTS_DEG].assign(**cols).to_csv(src, index=False)
        code, text = exit_code(program.main, [str(src)], capsys)
        assert code == 2 and said in text and "target_r" in text, text


def test_a_waypoint_near_the_wrist_singularity_is_not_swung_into_another_configuration(in_trained_project, tmp_path):
    """An offline waypoint's answer is a compensation of its joints (on the twin's campaign-like poses ≤ 1.5°).
    Near the wrist's singularity (joint 5 near 0°) the pose's six equations are met only by turning joints 2-4
    and 6 tens of degrees (a self-motion: measured 146° on joint 4 at joint 5 = 0.1°): such an answer is
    another configuration, a sweep of the arm between waypoints 0.4° apart, and must not become a move."""
    src = tmp_path / "wrist.csv"
    src.write_text("point_id,j1_deg,j2_deg,j3_deg,j4_deg,j5_deg,j6_deg\nA,10,-70,100,-120,60,30\n"
                   "S,10,-70,100,-120,0.1,30\n")
    table = program.run([str(src), "--comment-out-unreached"])
    script = (tmp_path / "wrist_comp.script").read_text()
    assert script.count("movej(") == 1 and "# S: NOT REACHED" in script and "joint 4 turned" in script
    kept = table.point_id != "S"
    assert (np.abs(table[JCOMP_DEG].to_numpy() - table[JOINTS_DEG].to_numpy())[kept.to_numpy()] < 5).all()


def test_the_configuration_is_named_by_its_singularities_by_hand():
    """poses.configuration on the nominal UR5: the wrist is sin q5's sign, the elbow sin q3's, the shoulder the
    side of joint 2's axis the wrist centre lies on (arm upright at q2 = -90°: leaning forward or back). The
    wrist-flipped twin of a pose (scipy from q4 + 180°, -q5, q6 + 180°) is the same flange pose, another one;
    another_configuration names it, and a joint turned more than 180°, but not a crossing within 5° (a
    compensation at the singularity) nor 20° on joint 1 (the same configuration); nor, for a target without
    an orientation, the wrist's sign (the flange's orientation is free)."""
    from scipy.optimize import least_squares
    from pipeline.lib.robot.kinematics import link_frames, nominal_geometry
    from pipeline.lib.robot.poses import configuration_margin
    from pipeline.lib.runtime.waypoints import another_configuration
    configuration = lambda q, g: np.sign(configuration_margin(q, g))             # (n, 3): the sides
    g = nominal_geometry(nominal_robot("ur5"))
    q = np.array([10.0, -70.0, 100.0, -120.0, 40.0, 30.0])
    pose = lambda x: link_frames(torch.as_tensor(np.radians(np.atleast_2d(x))), g)[:, 6].numpy()[0]
    met = lambda x: np.r_[pose(x)[:3, 3] - pose(q)[:3, 3], 1000 * (pose(x)[:3, :3] - pose(q)[:3, :3]).ravel()]
    flip = least_squares(met, q + [0, 0, 0, 180, -80, 180], method="lm", xtol=1e-15).x    # UR's wrist is not
    np.testing.assert_allclose(pose(flip), pose(q), atol=1e-9)     # spherical: joints 2-4 move too; same pose
    upright = np.array([[0, -80, 0, -90, 40, 0], [0, -100, 0, -90, 40, 0], [0, -90, 60, -90, 40, 0],
                        [0, -90, -60, -90, 40, 0], [0, -90, 60, -90, -40, 0]], float)
    s = configuration(upright, g)
    assert s[0, 0] == -s[1, 0] and s[2, 1] == -s[3, 1] and s[2, 2] == -s[4, 2]
    assert (s[2, :2] == s[4, :2]).all() and s[0, 1:].tolist() == s[1, 1:].tolist()
    turned = q + [0, 0, 0, 0, 0, 200]
    crossing = (q + [0, 0, 0, 0, -39, 0], q + [0, 0, 0, 0, -41, 0])                   # joint 5: 1° -> -1°
    why = another_configuration(np.stack([q, q, crossing[0], q]), np.stack([flip, turned, crossing[1], q + [20, 0, 0, 0, 0, 0]]), g)
    assert "configuration than the given joints': the wrist flipped" in why[0] and "joint 5 40.0° -> -" in why[0]
    assert "joint 6 turned 200.0° (the same angle lies 160.0° the other way round)" in why[1], why
    assert why[2:] == [None, None], why
    wrist = q + [0, 0, 0, 30, -80, 0]                                             # joint 5: 40° -> -40°
    assert "the wrist flipped" in another_configuration(q, wrist, g)[0]
    assert another_configuration(q, wrist, g, orientation=False) == [None]        # a position target: free
    home = np.array([0.0, -90.0, 0.0, -90.0, 0.0, 0.0])                          # UR's home: on every singularity
    assert (configuration(home, g) == 0).all()                                    # (was rounding's sign)
    assert another_configuration(home, [8.0, -80.0, -15.0, -85.0, 12.0, 4.0], g) == [None]     # a move from it


def test_the_elbow_of_an_arm_with_an_offset_forearm_is_where_it_stretches():
    """A custom chain (a PUMA 560's DH, its forearm offset: a3 20 mm, d4 432 mm) is stretched at q3 = -87°,
    not at 0°: a 7° move through q3 = 0 keeps its configuration (was refused as the elbow flipped), one
    through -87° flips it."""
    from pipeline.lib.robot.kinematics import nominal_geometry
    from pipeline.lib.robot.poses import configuration_margin
    from pipeline.lib.runtime.waypoints import another_configuration
    puma = load_robot({"model": "custom", "dh": {"d": [0, 0, 150.05, 431.8, 0, 0], "a": [0, 431.8, 20.32, 0, 0, 0],
                       "alpha_deg": [90, 0, -90, 90, -90, 0], "offset_deg": [0] * 6}, "joint_limits_deg": None,
                       "tool_mm": [0, 0, 0], "tcp": None})
    g = nominal_geometry(puma)
    q3 = np.linspace(-180, 180, 3601)
    m = configuration_margin(np.stack([np.zeros_like(q3), np.full_like(q3, 30.0), q3, *[np.zeros_like(q3)] * 2,
                                       np.zeros_like(q3)], 1) + [0, 0, 0, 0, 40, 0], g)[:, 1]
    crossings = q3[1:][np.diff(np.sign(m)) != 0]
    np.testing.assert_allclose(sorted(crossings), [-87.3, 92.7], atol=0.2)
    q0 = np.array([0.0, 30.0, 3.0, 0.0, 40.0, 0.0])
    assert another_configuration(q0, q0 + [4, 2, -7, 2, -2, 0], g, orientation=False) == [None]
    assert "the elbow flipped" in another_configuration(q0 - [0, 0, 80, 0, 0, 0], q0 - [0, 0, 95, 0, 0, 0], g)[0]


def test_a_pose_target_solved_into_another_configuration_never_becomes_a_move(in_trained_project, tmp_path):
    """An explicit target's joints are where to start from. Given the joints with joint 5 mirrored (-25° for
    a pose at +25°), lm reaches the pose by turning joint 5 through the wrist's singularity: the target is
    met, in another configuration than the program's, and a movej there would turn joint 5 50° from the
    joints the program gave. Not a move (before: written as a move, 'residual 0.0000 mm'); the same target from
    joints 3° off is."""
    from scipy.spatial.transform import Rotation
    from pipeline.lib.runtime.compensation import nominal_flange
    from pipeline.lib.project.config import read_json
    from pipeline.lib.robot.geometry import theory_geometry
    from pipeline.lib.robot.kinematics import tool_rotation
    robot = load_robot(in_trained_project["robot"])
    nominal = theory_geometry(robot, read_json("reports/frame.json")["tool_mm"])
    q = np.array([[10.0, -70.0, 100.0, -120.0, 25.0, 30.0]] * 2)
    given = q + [[0, 0, 0, 0, -50, 0], [3, -3, 3, -3, 3, -3]]
    probe = nominal_flange(q, nominal) @ tool_rotation(served_model().physics.geometry()).numpy()   # its frame
    rv = Rotation.from_matrix(probe).as_rotvec()
    p = fk_numpy(q, robot, nominal)
    src = tmp_path / "far.csv"
    pd.DataFrame(given, columns=JOINTS_DEG).assign(point_id=["FLIP", "NEAR"], **dict(zip(TARGET, p.T)),
                                                  **dict(zip(["target_rx", "target_ry", "target_rz"], rv.T))
                                                  ).to_csv(src, index=False)
    table = program.run([str(src), "--comment-out-unreached"]).set_index("point_id")
    assert table.converged.all() and table.orientation_residual_arcsec.max() < 1.0      # both reached
    np.testing.assert_allclose(table.loc["FLIP", JCOMP_DEG].to_numpy(float)[4], 25.0, atol=1.0)   # joint 5 at +25°
    script = (tmp_path / "far_comp.script").read_text()
    assert script.count("movej(") == 1 and "# FLIP: NOT REACHED" in script and "the wrist flipped" in script
    assert "# NEAR: residual" in script


def test_a_tcp_measured_in_the_probes_frame_lands_where_the_drawings_misses(in_trained_project, tmp_path):
    """robot.tcp in the calibrated flange frame cannot be the drawing's: joint 6's zero, the last twist, a6 and
    d6 trade exactly against the probe's mount, so the calibrated flange sits 0.43 mm and ~220″ off the
    mechanical one on the twin. A TCP 150 mm along the mechanical flange's x, entered from the drawing,
    lands ~0.45 mm off its targets on the twin; the same point entered where a tracker measures it, in the
    probe's frame (`frame: probe`), within a tenth of a millimetre."""
    import shutil
    import yaml
    from pipeline.lib.project.config import read_json
    from pipeline.lib.robot.frames import to_base
    from pipeline.lib.robot.geometry import theory_geometry
    from pipeline.lib.robot.kinematics import TOOL_ROT, rotation_xyz
    from pipeline.lib.sim.twin import Twin
    params = in_trained_project
    twin, frame = Twin.from_json(params["compensate"]["twin"]), read_json("reports/frame.json")
    t, R_T = twin.geometry["tool"].numpy(), rotation_xyz(twin.geometry[TOOL_ROT]).numpy()    # the true mount
    drawing = np.array([150.0, 0.0, 0.0])                        # the tool tip in the mechanical flange frame
    x = R_T.T @ (drawing - t)                                    # the same point in the probe's frame
    project = tmp_path / "cell"
    for f in ("models/boter.pt", "models/workspace.json", "reports/frame.json"):
        (project / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(f, project / f)
    cell = yaml.safe_load(open("params.yaml"))
    cell["robot"]["tcp"] = {"drawing": {"xyz_mm": drawing.tolist()},
                            "measured": {"xyz_mm": x.tolist(), "frame": "probe"}}
    (project / "params.yaml").write_text(yaml.safe_dump(cell))
    pts = load_points().query("split == 'test'").head(30)
    q = pts[JOINTS_DEG].to_numpy()
    robot = load_robot(params["robot"])
    target = fk_numpy(q, robot, theory_geometry(robot, drawing.tolist())) + [0.0, 0.0, 2.0]     # 2 mm above
    src = tmp_path / "prog.csv"
    pts[JOINTS_DEG].assign(**dict(zip(TARGET, target.T))).to_csv(src, index=False)

    def landed(name):                                            # where the twin puts the tool tip, base frame
        table = program.run([str(src), "--tcp", name, "--project", str(project), "--out", str(tmp_path / f"{name}.csv"),
                             "--urscript", str(tmp_path / f"{name}.script")])
        assert table.converged.all()
        p, R = twin.expected_pose(table[JCOMP_DEG].to_numpy())
        return np.linalg.norm(to_base(twin.to_tracker(p + R @ x), frame) - target, axis=1)
    measured, drawn = landed("measured"), landed("drawing")           # measured here: 0.038 (max 0.086) and
                                                                      # 0.469 (max 0.524) mm on 30 test poses
    assert measured.mean() < 0.1 and measured.max() < 0.3, measured
    assert drawn.mean() > 0.3 and drawn.mean() > 4 * measured.mean(), (drawn.mean(), measured.mean())

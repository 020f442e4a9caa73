"""The measurement planner (issue 23): what to measure so that a program lies inside the trained workspace.

`python -m pipeline.commands.plan PROGRAM.csv --n N --out DIR` on a small trained project (conftest.trained_project),
for a program at the side of the arm, where the twin's default campaign never went; and the library
(lib/planner/, lib/robot/poses.py) on the twin: acceptability, the tour, D-optimality against random
choice, and the predicted standard errors against a Monte Carlo identification.
"""
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from conftest import exit_code
from pipeline.commands import plan as plan_cmd
from pipeline.lib.learning.workspace import Workspace
from pipeline.lib.planner import coverage, design, planning, tour
from pipeline.lib.project.artifacts import FRAME_JSON
from pipeline.lib.project.columns import JOINTS_DEG
from pipeline.lib.project.config import load_params, read_json
from pipeline.lib.robot import poses
from pipeline.lib.robot.errormaps import coverage as angle_coverage
from pipeline.lib.robot.identify import geometry_jacobian, identifiability, identify
from pipeline.lib.robot.geometry import theory_geometry
from pipeline.lib.robot.kinematics import DTYPE, fk, fk_numpy, nominal_geometry
from pipeline.lib.robot.poses import RULES
from pipeline.lib.robot.robots import load_robot
from pipeline.lib.sim.twin import REGIONS, Twin, sample_poses, true_geometry

N = 16
TRACKER_MM = [-1200.0, -2600.0, 900.0]          # a new tracker placement facing the side of the arm



@pytest.fixture(scope="module")
def side_plan(trained_project, tmp_path_factory):
    """A 6-waypoint program at the side of the arm (joint 1 at 70-150°), planned for N poses from a new
    tracker placement: (its folder, the waypoints (6, 6) deg, plan.json, params)."""
    mp = pytest.MonkeyPatch()
    mp.chdir(trained_project)
    tmp = tmp_path_factory.mktemp("plan")
    q_wp = sample_poses(6, np.random.default_rng(11), region="side")
    src = tmp / "side.csv"
    pd.DataFrame(q_wp, columns=JOINTS_DEG).assign(point_id=[f"S{i}" for i in range(6)]).to_csv(src, index=False)
    out = tmp / "campaign"
    rep = plan_cmd.run([str(src), "--n", str(N), "--out", str(out), "--tracker-mm", *map(str, TRACKER_MM)])
    params = load_params()
    yield out, q_wp, rep, params
    mp.undo()


def test_the_three_files_with_their_names_and_columns(side_plan):
    out, q_wp, rep, _ = side_plan
    assert sorted(p.name for p in out.iterdir()) == sorted(plan_cmd.FILES)
    poses_csv = pd.read_csv(out / "poses.csv")
    assert list(poses_csv.columns) == ["pose_id"] + JOINTS_DEG and len(poses_csv) == N
    assert poses_csv.pose_id.tolist() == [f"M{i + 1:03d}" for i in range(N)]
    on_disk = json.loads((out / "plan.json").read_text())
    assert on_disk["n_planned"] == N and on_disk["criterion"]["name"] == planning.CRITERION
    assert {"before", "after", "after_expected_split"} <= set(on_disk["coverage"])
    ident = on_disk["identifiability"]
    for when in ("before", "after"):
        assert ident[when]["condition_number"] > 1 and all(v["se"] > 0 for v in ident[when]["se"].values())
    assert set(ident["after"]["se"]) == set(ident["parameters"]) and "station_tx" in ident["after"]["se"]
    assert set(ident["before"]["se"]) == set(ident["parameters"]) - set(design.STATION_NAMES)
    maps = ident["angle_maps"]                  # the program's uncovered joint (1) in the criterion, with its priors
    assert maps["joints"] == [1] and maps["joint1"]["after"]["mean_arcsec"] < maps["joint1"]["before"]["mean_arcsec"]
    assert on_disk["candidates"]["made"]["link"] > 0              # a new station may measure old poses again
    for k, se in ident["reported_se"].items():           # before the plan: the calibration's own se, recomputed
        assert ident["before"]["se"][k]["se"] == pytest.approx(se, rel=0.02)
        assert ident["after"]["se"][k]["se"] <= ident["before"]["se"][k]["se"] * (1 + 1e-9)
    t = on_disk["travel"]
    assert t["steps"] == N - 1 and 0 < t["max_joint_deg"] <= t["nearest_neighbour_only"]["max_joint_deg"] + 1e-6
    q = poses_csv[JOINTS_DEG].to_numpy()
    assert t["max_joint_deg"] == pytest.approx(np.abs(np.diff(q, axis=0)).max(1).sum(), rel=1e-6)
    assert [p["pose_id"] for p in on_disk["poses"]] == poses_csv.pose_id.tolist()


def test_the_urscript_holds_only_formatted_numbers_and_fixed_text(side_plan):
    out, *_ = side_plan
    script = (out / "measure.script").read_text()
    number = r"-?[0-9]+\.[0-9]+"
    allowed = [r"# measurement campaign planned by `python -m pipeline\.commands\.plan`: [0-9]+ poses, [0-9.]+ s at each for "
               r"the tracker", r"def measure_campaign\(\):", rf"  (acc|vel|settle) = {number}", r"  # M[0-9]{3,}",
               rf"  movej\(\[{number}(, {number}){{5}}\], a=acc, v=vel\)", r"  sleep\(settle\)", r"end"]
    lines = script.rstrip("\n").split("\n")
    for line in lines:
        assert any(re.fullmatch(a, line) for a in allowed), line
    assert lines[1] == "def measure_campaign():" and lines[-1] == "end"
    moves = re.findall(r"movej\(\[([^\]]+)\]", script)
    q_script = np.array([[float(v) for v in m.split(", ")] for m in moves])
    q_csv = np.radians(pd.read_csv(out / "poses.csv")[JOINTS_DEG].to_numpy())
    assert q_script.shape == (N, 6)
    np.testing.assert_allclose(q_script, q_csv, rtol=0, atol=1e-9)
    assert script.count("sleep(settle)") == N and "popup" not in script


def test_the_handshake_is_fixed_text_around_a_formatted_number():
    cfg = {"acc": 1.0, "vel": 0.5, "settle_s": 1.5, "handshake_io": 3}
    s = plan_cmd.measure_script(np.zeros((2, 6)), cfg)
    assert s.count("  set_standard_digital_out(3, True)\n  while not get_standard_digital_in(3):\n    sync()\n"
                   "  end\n  set_standard_digital_out(3, False)") == 2
    for bad in ({"handshake_io": "1); popup(\"x\""}, {"handshake_io": 9}, {"settle_s": float("nan")},
                {"acc": "1.0"}, {"vel": -1.0}):
        with pytest.raises(ValueError, match=r"params.yaml plan\."):
            plan_cmd.measure_script(np.zeros((1, 6)), {**cfg, **bad})


def test_plan_into_the_benchmark_records_is_refused(in_trained_project, tmp_path, capsys):
    """The defect (a review): `--out reports/bench` replaced the committed benchmark record plan.json."""
    src = tmp_path / "prog.csv"
    pd.DataFrame(sample_poses(2, np.random.default_rng(1)), columns=JOINTS_DEG).to_csv(src, index=False)
    before = Path("reports/bench/plan.json").read_bytes() if Path("reports/bench/plan.json").exists() else None
    code, said = exit_code(plan_cmd.main, [str(src), "--n", "2", "--out", "reports/bench"], capsys)
    assert code == 2 and re.search(r"reports/bench/\S+ is the project's own reports/bench \(", said), said
    after = Path("reports/bench/plan.json").read_bytes() if Path("reports/bench/plan.json").exists() else None
    assert after == before


def test_a_programs_orientation_columns_are_said_not_used(in_trained_project, tmp_path, capsys):
    """target_rx..rz were dropped unseen (the same plan with and without them); now plan.json and the
    summary say they were not used."""
    q = sample_poses(2, np.random.default_rng(1), region="side")
    robot = load_robot(in_trained_project["robot"])
    src = tmp_path / "prog.csv"
    df = pd.DataFrame(q, columns=JOINTS_DEG)
    df[["target_x", "target_y", "target_z"]] = fk_numpy(q, robot, theory_geometry(robot, read_json(FRAME_JSON)["tool_mm"]))
    df[["target_rx", "target_ry", "target_rz"]] = [[0.0, 3.0, 0.0], [1.0, 0.5, 0.2]]
    df.to_csv(src, index=False)
    code, said = exit_code(plan_cmd.main, [str(src), "--n", "4", "--out", str(tmp_path / "o")], capsys)
    rep = json.loads((tmp_path / "o/plan.json").read_text())
    assert code == 0 and rep["columns_not_used"] == ["target_rx", "target_ry", "target_rz"], said
    assert "target_rx, target_ry, target_rz not used" in said and len(pd.read_csv(tmp_path / "o/poses.csv")) == 4


def test_a_target_reached_only_in_another_configuration_is_refused_as_the_program_compensator_refuses_it(
        in_trained_project, tmp_path, capsys):
    """A review (2026-12-06, evening): the planner solved a program's targets to joints without the program
    compensator's configuration rule, so it planned measurement poses (j3 ≈ 225°) around a shoulder and elbow
    flip that `program` refuses. Now the plan is refused, naming the waypoint; nothing written."""
    from pipeline.commands import program as program_cmd
    robot = load_robot(in_trained_project["robot"])
    q = np.array([[13.496139, -54.644684, 121.723304, 85.024776, 148.906262, 55.641267]] * 2)
    src = tmp_path / "prog.csv"
    df = pd.DataFrame(q, columns=JOINTS_DEG)
    df.insert(0, "point_id", ["A", "B"])                        # A: its own joints' position; B: over the base
    df[["target_x", "target_y", "target_z"]] = np.vstack([
        fk_numpy(q[:1], robot, theory_geometry(robot, read_json(FRAME_JSON)["tool_mm"])), [[300.0, 100.0, 300.0]]])
    df.to_csv(src, index=False)
    code, said = exit_code(plan_cmd.main, [str(src), "--n", "3", "--out", str(tmp_path / "o")], capsys)
    assert code == 1 and "1 target(s) the calibrated arm reaches only in another configuration" in said, said
    assert re.search(r"B: another configuration than the given joints': the shoulder flipped, the elbow flipped "
                     r"\(joint 3 turned \d+\.\d°", said) and "A: " not in said and "Traceback" not in said, said
    assert not (tmp_path / "o").exists()
    code, said = exit_code(program_cmd.main, [str(src), "--out", str(tmp_path / "c.csv"), "--urscript",
                                              str(tmp_path / "c.script")], capsys)
    assert code == 1 and "NOT REACHED B: " in said and "the shoulder flipped, the elbow flipped" in said, said


def test_every_planned_pose_is_within_the_limits_and_acceptable(side_plan):
    out, _, rep, params = side_plan
    robot = load_robot(params["robot"])
    q = pd.read_csv(out / "poses.csv")[JOINTS_DEG].to_numpy()
    assert not robot.check_joints(q).any()
    g = nominal_geometry(robot)
    failed = poses.rejected(q, g, params["plan"]["rules"], robot.limits_deg, tracker_mm=TRACKER_MM)
    assert not any(failed), failed
    assert "tracker_side_deg" in poses.checks(q, g, params["plan"]["rules"], tracker_mm=TRACKER_MM)
    assert (np.abs(np.sin(np.radians(q[:, 4]))) > params["plan"]["rules"]["sin_wrist"]).all()   # no singular wrist
    moves = re.findall(r"movej\(\[([^\]]+)\]", (out / "measure.script").read_text())     # what the robot runs
    q_run = np.degrees([[float(v) for v in m.split(", ")] for m in moves])
    assert poses.moves_clear(q_run[:-1], q_run[1:], g, params["plan"]["rules"]).all()
    assert json.loads((out / "plan.json").read_text())["travel"]["clearance"]["checked"]
    assert rep["tracker"] == {"station": None, "new_station": True, "position_mm": TRACKER_MM, "side_rule_deg": 90.0}


def test_a_side_program_goes_from_outside_to_inside_the_trained_workspace(side_plan):
    """Recomputed with Workspace.parts itself: the training poses plus the planned ones (same radius,
    the angle maps' coverage by errormaps.coverage with the parts settings)."""
    out, q_wp, rep, params = side_plan
    ws = Workspace.from_dict(read_json("models/workspace.json"))
    before = ws.parts(q_wp)
    assert before["network"].mean() <= 1 / 6 and before["angle_map"].mean() <= 1 / 6
    q = pd.read_csv(out / "poses.csv")[JOINTS_DEG].to_numpy()
    train = np.vstack([ws.train_q, q])
    a = params["parts"]["angle_map"]
    cover = angle_coverage(train, [j + 1 for j in np.flatnonzero(ws.angle_cover.any(1))], a["reach_deg"],
                           a["fade_deg"])
    after = Workspace(train, ws.radius, 0, 0, 0, None, cover).parts(q_wp)
    assert after["network"].all() and after["angle_map"].all()
    c = rep["coverage"]
    assert c["before"]["all"] <= 1 / 6 and c["after"]["all"] == 1.0 and c["parts_short_after"] == 0
    assert 0.8 <= c["after_expected_split"] <= 1.0
    assert rep["n_coverage"] >= 1 and all(w["after"]["all"] for w in c["per_waypoint"])


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.assign(j2_deg=["1.0", "x", "2", "3"]), r"row 3, column 'j2_deg': not a finite number"),
    (lambda d: d.drop(columns="j5_deg"), r"column 'j5_deg': missing waypoint column 'j5_deg'"),
    (lambda d: d.assign(j4_deg=[0.0, 0.0, 500.0, 0.0]), r"row 4, column 'j4_deg': 500.0° beyond the joint limits"),
    (lambda d: d.assign(point_id=["a", "b); popup(1", "c", "d"]), r"row 3, column .point_id.: point id"),
    (lambda d: d * 0.01, r"look like radians"),
])
def test_bad_waypoints_are_named_by_file_row_and_column(in_trained_project, tmp_path, capsys, edit, message):
    src = tmp_path / "bad.csv"
    edit(pd.DataFrame(np.tile([[100.0, -80.0, 100.0, -110.0, 80.0, 10.0]], (4, 1)), columns=JOINTS_DEG)).to_csv(
        src, index=False)
    code, said = exit_code(plan_cmd.main, [str(src), "--n", "5", "--out", str(tmp_path / "o")], capsys)
    assert code == 2 and re.search(message, said) and str(src) in said and "Traceback" not in said, said
    assert said.count("\n") == 1 and not (tmp_path / "o").exists()


def test_bad_arguments_are_refused(in_trained_project, tmp_path, capsys):
    src = tmp_path / "ok.csv"
    pd.DataFrame(sample_poses(2, np.random.default_rng(1), region="side"), columns=JOINTS_DEG).to_csv(src, index=False)
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for argv, message in (([str(src), "--n", "0", "--out", str(tmp_path / "o")], "--n 0: plan at least 1 pose"),
                          ([str(src), "--n", "3", "--out", str(a_file)], "a file, not a folder"),
                          ([str(src), "--n", "3", "--out", str(tmp_path), "--station", "nowhere"],
                           "not a station of reports/frame.json"),
                          ([str(tmp_path / "none.csv"), "--n", "3", "--out", str(tmp_path / "o")], "no such file"),
                          ([str(src), "--n", "3", "--out", str(tmp_path / "o"), "--seed", "-1"],   # was numpy's words
                           "--seed -1: an integer >= 0"),
                          ([str(src), "--n", "3", "--out", str(tmp_path / "o"), "--tracker-mm", "1e308", "1e308", "0"],
                           "--tracker-mm: three numbers within 100000 mm of the base"),   # was Infinity in plan.json
                          ([str(src), "--n", "100000", "--out", str(tmp_path / "o")],   # a review: minutes without a
                           "--n 100000: only ")):                                         # word, every candidate planned
        code, said = exit_code(plan_cmd.main, argv, capsys)
        assert code == 2 and message in said and "Traceback" not in said, said
    assert a_file.read_text() == "x" and not (tmp_path / "o").exists()


# ----------------------------------------------------------------------------- the library, on the twin

def test_the_singularity_rules_judge_the_chains_own_angles_however_its_table_is_written():
    """Review (2026-11-29): sin_elbow and sin_wrist read the raw q3, q5, so a custom table with joints 3 and 5
    re-zeroed (offset_deg 90) had the stretched elbow and the singular wrist pass, and good poses fail."""
    ur5 = {"d": [89.159, 0, 0, 109.15, 94.65, 82.3], "a": [0, -425.0, -392.25, 0, 0, 0], "alpha_deg": [90, 0, 0, 90, -90, 0]}
    def geometry(offset):
        return nominal_geometry(load_robot({"model": "custom", "dh": {**ur5, "offset_deg": offset},
                                            "joint_limits_deg": None, "tool_mm": [0, 0, 0], "tcp": None}))
    shift = np.array([0, 0, 90, 0, 90, 0], float)
    phys = np.array([[10.0, -60.0, 0.0, -90.0, 0.0, 30.0],             # elbow stretched, wrist singular
                     [10.0, -60.0, 70.0, -90.0, 60.0, 30.0]])          # both well bent
    rules = {"sin_elbow": 0.15, "sin_wrist": 0.2}
    as_is, rezeroed = poses.checks(phys, geometry([0] * 6), rules), poses.checks(phys - shift, geometry(shift), rules)
    for c in (as_is, rezeroed):
        assert c["sin_elbow"].tolist() == c["sin_wrist"].tolist() == [False, True]


def test_program_joints_says_which_targets_it_reaches_only_in_another_configuration():
    """program_joints judges its answers by the program compensator's rule (waypoints.another_configuration,
    position targets: the wrist free): a target near its joints' position is reached in their configuration,
    one over the base from the same joints only by turning joint 3 some 90° through the shoulder's and the
    elbow's singularities."""
    from pipeline.lib.planner.candidates import program_joints
    robot = load_robot({"model": "ur5", "dh": None, "joint_limits_deg": None, "tcp": None, "tool_mm": [0, 0, 109.0]})
    g = nominal_geometry(robot)
    q0 = np.array([[13.496139, -54.644684, 121.723304, 85.024776, 148.906262, 55.641267]] * 2)
    target = np.vstack([fk_numpy(q0[:1] + [5.0, -3.0, 4.0, 0.0, 2.0, 0.0], robot, g), [[300.0, 100.0, 300.0]]])
    q, miss, why = program_joints(q0, target, g, robot.limits_deg)
    assert miss.max() < 1e-6 and np.abs(q[0] - q0[0]).max() < 5.0 and why[0] is None
    assert 80.0 < q[1, 2] - q0[1, 2] < 100.0
    assert why[1].startswith("another configuration than the given joints': the shoulder flipped, the elbow flipped")


def test_program_joints_from_urs_home_reach_their_targets_in_its_configuration():
    """A review (2026-12-06, evening): from UR's home (q3 = q5 = 0, the elbow and the wrist at their
    singularities) the undamped steps spun joints past 360° (joint 2 turned 362.8°, joint 4 428.6°) or fell 4.9 mm
    short, so the planner refused targets 30-100 mm away that the program compensator reaches. Each step is now
    at most MAX_STEP_RAD a joint: every target reached, each joint within 70° of home, no configuration said."""
    from pipeline.lib.planner.candidates import program_joints
    robot = load_robot({"model": "ur5", "dh": None, "joint_limits_deg": None, "tcp": None, "tool_mm": [0, 0, 109.0]})
    g = nominal_geometry(robot)
    home = np.array([[0.0, -90.0, 0.0, -90.0, 0.0, 0.0]] * 3)
    target = fk_numpy(home[:1], robot, g) + np.array([[30.0, 0.0, 30.0], [80.0, 0.0, -20.0], [0.0, 50.0, 0.0]])
    q, miss, why = program_joints(home, target, g, robot.limits_deg)
    assert miss.max() < 1e-6 and np.abs(q - home).max() < 70.0 and why == [None] * 3, (miss, q, why)


def test_the_twin_samples_by_the_library_rules():
    """twin.sample_poses keeps exactly the poses poses.acceptable accepts (RULES in the region's window)."""
    g = nominal_geometry(Twin().robot)
    q = np.round(np.random.default_rng(3).uniform([-60, -160, -160, -270, -160, -180], [60, -20, 160, 90, 160, 180],
                                                  (2000, 6)), 6)
    ok = poses.acceptable(q, g, RULES, azimuth_deg=REGIONS["front"][1])
    assert 0 < ok.sum() < len(q)
    q_s = sample_poses(50, np.random.default_rng(4))
    assert poses.acceptable(q_s, g, RULES, azimuth_deg=REGIONS["front"][1]).all()
    assert not poses.acceptable(q_s, g, RULES, azimuth_deg=REGIONS["side"][1]).any()
    behind = poses.checks(q_s, g, RULES, tracker_mm=[3000.0, 0.0, 500.0])["tracker_side_deg"]     # tracker behind
    facing = poses.checks(q_s, g, RULES, tracker_mm=[-3000.0, 0.0, 500.0])["tracker_side_deg"]    # in front
    assert facing.all() and not behind.any()


def test_the_tour_visits_every_pose_once_and_2opt_shortens_it():
    rng = np.random.default_rng(0)
    line = np.zeros((12, 6))
    line[:, 0] = np.arange(12) * 10.0
    perm = rng.permutation(12)
    order = tour.tour(line[perm], start=int(np.argmin(perm)))
    assert sorted(order) == list(range(12)) and perm[order[0]] == 0
    assert tour.travel(line[perm][order])["max_joint_deg"] == pytest.approx(110.0)      # straight along the line
    q = rng.uniform(-90, 90, (40, 6))
    nn, opt = tour.tour(q, 0, passes=0), tour.tour(q, 0)
    assert sorted(opt) == list(range(40)) and opt[0] == 0
    assert tour.travel(q[opt])["max_joint_deg"] <= tour.travel(q[nn])["max_joint_deg"]


def test_a_move_between_two_acceptable_poses_through_the_table_is_not_clear():
    """Two poses of a 200-pose plan of data/examples/waypoints.csv, each clear of the table (the wrist frames
    43 and 86 mm above it; the rule: 40): the movej between them took the wrist 3 mm into the table (half
    way), and the measurement script made it."""
    g = nominal_geometry(Twin().robot)
    a = np.array([-17.1, -50.5, 123.0, 48.3, 21.8, 25.1])
    b = np.array([-53.3, -26.9, 37.9, 19.7, 112.4, -50.5])
    assert poses.acceptable(np.stack([a, b]), g, RULES).all()
    half = poses.origins([(a + b) / 2], g)[0, 3:, 2]                     # the wrist frames' heights half way
    assert half.min() < 0.0
    assert not poses.moves_clear(a, b, g, RULES)[0] and not poses.moves_clear(b, a, g, RULES)[0]
    assert poses.moves_clear(a, a + 0.1 * (b - a), g, RULES)[0]           # the first tenth of the way is clear
    assert poses.moves_clear(a, b, g, {**RULES, "table_mm": None})[0]     # only the rule that is on counts


def test_the_tour_takes_no_move_through_the_table_that_another_order_avoids():
    """The twin's 200 campaign poses (seed 4): the tour by joint distance alone moves once under the table's
    clearance; with the moves checked it visits every pose once, from the same start, every move clear, for
    a travel within 2% of the other."""
    g = nominal_geometry(Twin().robot)
    ok = lambda a, b: bool(poses.moves_clear(a, b, g, RULES)[0])
    q = sample_poses(200, np.random.default_rng(4))
    blind, seen = tour.tour(q, 0), tour.tour(q, 0, move_ok=ok)
    steps = lambda o: [ok(q[i], q[j]) for i, j in zip(o[:-1], o[1:])]
    assert not all(steps(blind))
    assert sorted(seen) == list(range(200)) and seen[0] == 0 and all(steps(seen))
    assert tour.travel(q[seen])["max_joint_deg"] < 1.02 * tour.travel(q[blind])["max_joint_deg"]


def test_a_move_no_order_avoids_goes_by_way_of_a_pose_both_ends_may_move_to():
    """Two poses 100° apart on joint 1 where no move may turn a joint more than 60°: by way of the pool's
    pose nearest both; none when the pool has no pose within 60° of both. The script moves there between
    the two measurements, measuring nothing."""
    ok = lambda a, b: bool(np.abs(a - b).max() <= 60.0)
    q = np.zeros((2, 6))
    q[1, 0] = 100.0
    pool = np.zeros((3, 6))
    pool[:, 0] = [-30.0, 45.0, 70.0]
    via = tour.vias(q, pool, ok)
    assert list(via) == [0] and via[0][0] == 45.0                        # 70 is within 60 of 100, not of 0
    assert tour.vias(q, pool[[0, 2]], ok) == {0: None}
    script = plan_cmd.measure_script(q, {"acc": 1.0, "vel": 0.5, "settle_s": 1.0, "handshake_io": None}, via)
    moves = re.findall(r"movej\(\[([^\]]+)\]", script)
    assert np.degrees([float(m.split(", ")[0]) for m in moves]).round(9).tolist() == [0.0, 45.0, 100.0]
    assert script.count("sleep(settle)") == 2 and "# via, not measured, to M002: the direct move breaks the clearance rules" in script


def test_the_script_goes_by_way_of_a_pose_where_the_direct_move_breaks_the_rules(in_trained_project, tmp_path,
                                                                              monkeypatch, capsys):
    """A two-pose plan whose one move is made to break the clearance rules (poses.moves_clear replaced: that
    move alone fails): the script goes from M001 by way of a candidate pose to M002, measuring nothing there,
    as plan.json says; every move it makes passes. A plan whose every move breaks them is refused: exit 1,
    nothing written, and the earlier plan's files in the folder named as not this program's."""
    src, first = tmp_path / "prog.csv", tmp_path / "first"
    q = sample_poses(2, np.random.default_rng(5))
    pd.DataFrame(q, columns=JOINTS_DEG).to_csv(src, index=False)
    plan_cmd.run([str(src), "--n", "2", "--out", str(first)])
    a, b = pd.read_csv(first / "poses.csv")[JOINTS_DEG].to_numpy()
    pair = lambda x, y: {tuple(np.round(x, 6)), tuple(np.round(y, 6))} == {tuple(np.round(a, 6)), tuple(np.round(b, 6))}
    monkeypatch.setattr(plan_cmd, "moves_clear", lambda x, y, g, r: np.array([not pair(np.ravel(x), np.ravel(y))]))
    out = tmp_path / "second"
    rep = plan_cmd.run([str(src), "--n", "2", "--out", str(out)])
    via = rep["travel"]["clearance"]["via"]
    assert [v["after"] for v in via] == ["M001"] and rep["travel"]["clearance"]["failing"] == []
    script = (out / "measure.script").read_text()
    moves = np.degrees([[float(v) for v in m.split(", ")] for m in re.findall(r"movej\(\[([^\]]+)\]", script)])
    assert len(moves) == 3 and script.count("sleep(settle)") == 2 and rep["travel"]["steps"] == 2
    np.testing.assert_allclose(moves[[0, 2]], [a, b], atol=1e-9)
    np.testing.assert_allclose(moves[1], via[0]["j_deg"], atol=1e-9)
    assert not pair(moves[0], moves[1]) and not pair(moves[1], moves[2])
    assert "  # via, not measured, to M002: the direct move breaks the clearance rules" in script.split("\n")
    monkeypatch.setattr(plan_cmd, "moves_clear", lambda x, y, g, r: np.array([False]))
    before = {f: (out / f).read_bytes() for f in plan_cmd.FILES}
    code, said = exit_code(plan_cmd.main, [str(src), "--n", "2", "--out", str(out)], capsys)
    assert code == 1 and "the move M001 -> M002 between planned poses breaks" in said, said
    assert (f"; {out / 'poses.csv'}, {out / 'measure.script'}, {out / 'plan.json'}: an earlier run's, left as they "
            "were, not this one's") in said
    assert {f: (out / f).read_bytes() for f in plan_cmd.FILES} == before
    code, said = exit_code(plan_cmd.main, [str(src), "--n", "2", "--out", str(tmp_path / "third")], capsys)
    assert code == 1 and not (tmp_path / "third").exists() and "earlier run" not in said


def twin_identification(q_deg, params, sigma):
    """The twin's identifiable parameters on poses q (names by identify.identifiability at nominal), as an
    Identification at the twin's true rigid geometry."""
    g = true_geometry(Twin().errors)
    cfg = params["calibrate"]
    J, spec = geometry_jacobian(torch.as_tensor(np.radians(q_deg), dtype=DTYPE), nominal_geometry(Twin().robot), cfg)
    keep = identifiability(J, [s[0] for s in spec], cfg["rank_tol"])["keep"]
    return design.Identification(g, cfg, [s[0] for s, k in zip(spec, keep) if k], sigma)


def scratch_plan(q_cand, n, ident, cover=False):
    """A plan with no training poses yet (from scratch), the candidates given."""
    cov = coverage.Coverage(np.zeros((0, 6)), 30.0, [], 3.0, 5.0)
    cand = {"q": q_cand, "near": np.full(len(q_cand), -1), "kind": np.array(["region"] * len(q_cand), object),
            "made": {}, "rejected_by": {}, "waypoints_acceptable": np.ones(0, bool)}
    return planning.plan(q_cand[:3], n, cov, ident, cand, cover=cover)


def log_det(ident, q):
    A = ident.rows(q, new=True)
    M = design.information(A)
    d = np.sqrt(np.diag(M))
    return np.linalg.slogdet(M / np.outer(d, d))[1] + 2 * np.log(d).sum()


def test_d_optimal_choice_beats_random_choice_on_log_det():
    params = load_params()
    q_cand = sample_poses(300, np.random.default_rng(21))
    ident = twin_identification(q_cand, params, 0.05)
    chosen = scratch_plan(q_cand, 50, ident).q_deg
    best = log_det(ident, chosen)
    rng = np.random.default_rng(22)
    random_ = [log_det(ident, q_cand[rng.choice(len(q_cand), 50, replace=False)]) for _ in range(20)]
    assert best > max(random_), (best, max(random_))


def test_predicted_standard_errors_agree_with_a_monte_carlo_identification():
    """The plan's sigma sqrt(diag((JᵀJ)⁻¹)) against the spread of identify() over 12 noisy measurements of
    the 40 planned poses on the twin's noise-free rigid geometry (Gaussian noise, sigma per coordinate);
    the geometric groups a, alpha, offset, beta and tool (small, for speed)."""
    params = load_params()
    params["calibrate"]["params"] = ["a", "alpha", "offset", "beta", "tool"]
    sigma = 0.05
    q_cand = sample_poses(200, np.random.default_rng(31))
    ident = twin_identification(q_cand, params, sigma)
    pl = scratch_plan(q_cand, 40, ident)
    predicted = pl.report["identifiability"]["after"]["se"]
    q = torch.as_tensor(np.radians(pl.q_deg), dtype=DTYPE)
    with torch.no_grad():
        p_true = fk(q, true_geometry(Twin().errors)).numpy()
    cfg = {**params["calibrate"], "loss": "linear"}
    rng = np.random.default_rng(32)
    runs = []
    for _ in range(12):
        _, rep = identify(q, p_true + rng.normal(0, sigma, p_true.shape), nominal_geometry(Twin().robot), cfg)
        assert rep["identified"] == ident.names
        runs.append([rep["estimates"][k]["delta"] for k in ident.names])
    ratio = np.std(runs, axis=0, ddof=1) / np.array([predicted[k]["se"] for k in ident.names])
    # 12 runs: a standard deviation is known to about ±21%; the median over the parameters much better
    assert 0.8 < np.median(ratio) < 1.2 and ratio.min() > 0.45 and ratio.max() < 1.7, dict(zip(ident.names, ratio))


def test_the_criterion_gain_is_the_log_det_increase():
    """DCriterion's sparse arithmetic (the map block's 4 columns per joint) against dense log dets, with a
    new station's columns and joint 1's angle map with its priors."""
    params = load_params()
    params["calibrate"]["params"] = ["a", "offset", "tool"]
    q_old, q_new = sample_poses(40, np.random.default_rng(41)), sample_poses(30, np.random.default_rng(42), region="side")
    ident = twin_identification(q_old, params, 0.05)
    ident.new_station = True
    block = design.MapBlock([1], 10.0, 300.0, 50.0, 0.1)
    g = ident.geometry
    crit = design.DCriterion(ident.rows(q_old, False), *block.rows(q_old, g), ident.rows(q_new, True),
                               *block.rows(q_new, g), block.precision())
    dense = crit.dense(crit.A, crit.vals, crit.idx)                               # (30, 3, P), scaled
    logdet = lambda M: np.linalg.slogdet(M)[1]
    gains = crit.gains(np.arange(30))
    for c in (0, 7, 29):
        assert gains[c] == pytest.approx(logdet(crit.M + dense[c].T @ dense[c]) - logdet(crit.M), rel=1e-7)
    M0 = crit.M.copy()
    crit.add(7)
    np.testing.assert_allclose(crit.M, M0 + dense[7].T @ dense[7])
    np.testing.assert_allclose(crit.Minv @ crit.M, np.eye(len(M0)), atol=1e-6)
    assert block.size == 36 and (dense[:, :, crit.Pc:] != 0).sum(-1).max() <= 4      # one joint: 4 knots a pose


def test_a_learning_curve_is_extended_only_with_the_settings_it_was_run_with(tmp_path, monkeypatch):
    """bench plan --curve --extend: the sizes it lacks are added to the curve already in plan.json, its runs
    kept; other seeds, overrides, epochs or work region are refused (they would mix two curves)."""
    from pipeline.commands.bench import plan as bench
    monkeypatch.setattr(bench, "OUT", tmp_path / "plan.json")
    rec = {"overrides": [], "epochs": None, "seeds": [139, 140], "work_waypoints": 40, "machine": {"cpu": "x"}}
    with pytest.raises(SystemExit, match="holds no 'learning_curve'"):
        bench.extended_curve("learning_curve", rec, [700])
    old = {**rec, "sizes": [25, 400], "runs": {"planned": {"25": {"139": {}}}, "random": {}}, "seconds": 9.0}
    bench.save("learning_curve", old)
    got, new = bench.extended_curve("learning_curve", dict(rec), [400, 700])
    assert new == [700] and got["sizes"] == [25, 400, 700] and got["runs"] == old["runs"]
    assert got["extensions"] == [{"sizes": [700], "machine": {"cpu": "x"}}] and got["seconds"] == 9.0
    with pytest.raises(SystemExit, match="seeds"):
        bench.extended_curve("learning_curve", {**rec, "seeds": [139]}, [700])


def test_a_matrix_whose_columns_repeat_identifies_nothing():
    """A mutation review: the rank check dropped (every column non-zero taken as identified) passed; the test
    below has a zero column. The twin's a2, a3, d4 and offset5 on 50 poses are identified; with offset5's column
    made d4's (two equal, non-zero columns): not identified, no condition number, no errors."""
    params = load_params()
    ident = design.Identification(true_geometry(Twin().errors), params["calibrate"], ["a2", "a3", "d4", "offset5"], 0.05)
    A = ident.rows(sample_poses(50, np.random.default_rng(3)), new=True).reshape(-1, 4)   # (150, 4) mm per unit
    assert design.prediction(A.T @ A, ident)["identified"]
    A[:, 3] = A[:, 2]
    got = design.prediction(A.T @ A, ident)
    assert not got["identified"] and got["condition_number"] is None
    assert all(v["se"] is None for v in got["se"].values())


def test_orientation_rows_identify_joint_6_which_positions_cannot():
    """A marker on joint 6's axis (the twin's, at the flange): positions alone leave offset6 (and the
    probe's rotation) unidentified, so the plan's prediction is None; the calibration fitted with orientation
    identifies them, and so does the planner with the same weighted orientation rows (calibrate's
    geometry_jacobian rows, 6 per pose), with finite standard errors for every parameter."""
    params = load_params()
    cfg, q = params["calibrate"], sample_poses(200, np.random.default_rng(3))
    g = true_geometry(Twin().errors)
    names = ["a5", "offset5", "offset6", "tool_ry"]                # in parameter_spec's order, as calibrate's
    weight = 286.4788975654116                                 # 0.05 mm / 36 arcsec
    pos = design.Identification(g, cfg, names, 0.05)
    pose = design.Identification(g, cfg, names, 0.05, weight=weight)
    A3, A6 = pos.rows(q, new=True), pose.rows(q, new=True)
    assert A3.shape == (200, 3, 4) and A6.shape == (200, 6, 4)
    np.testing.assert_array_equal(A6[:, :3], A3)                # the position rows are the same
    J = geometry_jacobian(torch.as_tensor(np.radians(q), dtype=DTYPE), g, cfg, names, weight)[0]
    np.testing.assert_allclose(A6.reshape(-1, 4), J, rtol=0, atol=1e-9)
    assert not design.prediction(design.information(A3), pos)["identified"]
    told = design.prediction(design.information(A6), pose)
    assert told["identified"] and all(0 < v["se"] < 1e-2 for v in told["se"].values())   # mm, deg (~2.5")
    block = design.MapBlock([6], 10.0, 300.0, 50.0, 0.05)      # joint 6's map: seen by orientation
    v3, _ = block.rows(q, g)
    v6, _ = block.rows(q, g, weight)
    np.testing.assert_array_equal(v6[:, :3], v3)              # the marker ~0.15 mm off joint 6's axis
    assert np.abs(v6[:, 3:]).max() > 1000 * np.abs(v3).max()

"""The robot catalogue (UR family) at hand-checked poses, and modified-DH tables for a custom arm."""
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.lib.project.config import load_params, section
from pipeline.lib.reading.presets import PRESETS, merged_params
from pipeline.lib.robot.kinematics import DTYPE, fk_numpy, fk_poses, nominal_geometry
from pipeline.lib.robot.robots import TABLES, UR_JOINTS, load_robot, nominal_robot

# Universal Robots' published DH lengths (mm): d1, a2, a3, d4, d5, d6; and the datasheet reach (mm)
UR = {
    "ur3": ((151.9, -243.65, -213.25, 112.35, 85.35, 81.9), 500),
    "ur5": ((89.159, -425.0, -392.25, 109.15, 94.65, 82.3), 850),
    "ur10": ((127.3, -612.0, -572.3, 163.941, 115.7, 92.2), 1300),
    "ur3e": ((151.85, -243.55, -213.2, 131.05, 85.35, 92.1), 500),
    "ur5e": ((162.5, -425.0, -392.2, 133.3, 99.7, 99.6), 850),
    "ur10e": ((180.7, -612.7, -571.55, 174.15, 119.85, 116.55), 1300),
    "ur16e": ((180.7, -478.4, -360.0, 174.15, 119.85, 116.55), 900),
    "ur20": ((236.3, -862.0, -728.7, 201.0, 159.3, 154.3), 1750),
    "ur30": ((236.3, -637.0, -503.7, 201.0, 159.3, 154.3), 1300),
}


def test_the_catalogue_is_the_ur_family():
    assert sorted(TABLES) == sorted(UR)


@pytest.mark.parametrize("name", sorted(UR))
def test_ur_flange_at_hand_checked_poses(name):
    """UR standard DH, alpha = 90, 0, 0, 90, -90, 0°, worked by hand:
    zero pose: joints 2-4 lie along base x (a2 + a3), d4 and d6 along base -y, d5 along base -z;
    q2 = q4 = -90°: a2 + a3 point up, then d5, so the arm stands straight up over (0, -(d4 + d6));
    q1 = 90°: the zero pose turned 90° about z, (x, y) -> (-y, x)."""
    (d1, a2, a3, d4, d5, d6), _ = UR[name]
    q = np.array([[0, 0, 0, 0, 0, 0], [0, -90, 0, -90, 0, 0], [90, 0, 0, 0, 0, 0]], float)
    expected = [[a2 + a3, -(d4 + d6), d1 - d5],
                [0.0, -(d4 + d6), d1 - (a2 + a3) + d5],
                [d4 + d6, a2 + a3, d1 - d5]]
    np.testing.assert_allclose(fk_numpy(q, nominal_robot(name)), expected, rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", sorted(UR))
def test_ur_reach_and_data(name):
    (d1, a2, a3, d4, d5, d6), reach = UR[name]
    robot = nominal_robot(name)
    assert robot.reach == pytest.approx(d1 - a2 - a3 + d4 + d5 + d6, abs=1e-9)
    assert -(a2 + a3) < reach < robot.reach          # the datasheet's reach: beyond the elbow span, within the bound
    np.testing.assert_array_equal(np.degrees(robot.alpha), [90, 0, 0, 90, -90, 0])
    np.testing.assert_array_equal(robot.limits_deg, [[-360, 360]] * 6)
    assert robot.joint_names == UR_JOINTS
    assert (robot.mass > 0).all() and robot.com.shape == (6, 3)
    assert (robot.effort_nm > 0).all() and (robot.velocity_rad_s > 0).all()
    assert robot.com[1, 0] == pytest.approx(-a2 / 2, rel=0.3)   # the upper arm's mass sits near its middle


@pytest.mark.parametrize("name, deg_s", [("ur5", [180] * 6), ("ur10", [120, 120, 180, 180, 180, 180])])
def test_joint_speed_limits_are_the_ur_descriptions(name, deg_s):
    """config/<model>/joint_limits.yaml of the UR ROS description (`!degrees 180.0` ...): the URDF's limits and the
    path command's default joint speeds. The UR5's were 3.15 rad/s, 0.27% above its 180°/s."""
    np.testing.assert_allclose(nominal_robot(name).velocity_rad_s, np.radians(deg_s), rtol=1e-15)


def mdh_flange(q_rad, alpha_prev, a_prev, d, offset):
    """Craig's modified-DH product T_1 ... T_6, T_i = Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i) Tz(d_i)."""
    def rx(t):
        c, s = np.cos(t), np.sin(t)
        return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]])

    def rz(t):
        c, s = np.cos(t), np.sin(t)
        return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])

    def trans(x, z):
        T = np.eye(4)
        T[0, 3], T[2, 3] = x, z
        return T

    out = []
    for q in q_rad:
        T = np.eye(4)
        for i in range(6):
            T = T @ rx(alpha_prev[i]) @ trans(a_prev[i], 0) @ rz(q[i] + offset[i]) @ trans(0, d[i])
        out.append(T)
    return np.array(out)


def custom(dh: dict, tool=(0.0, 0.0, 0.0)):
    return load_robot({"model": "custom", "dh": dh, "joint_limits_deg": None, "tcp": None, "tool_mm": list(tool)})


# Craig's PUMA 560 (Introduction to Robotics, table 3.4), rows alpha_{i-1}, a_{i-1}, d_i (mm), with a
# 56.25 mm flange on joint 6 and zero offsets that are not zero, so every term is exercised
PUMA = {"alpha_deg": [0, -90, 0, -90, 90, -90], "a": [0, 0, 431.8, 20.32, 0, 0],
        "d": [0, 0, 149.09, 433.07, 0, 56.25], "offset_deg": [5, -90, 12, 0, -7, 30], "convention": "modified"}


def test_modified_dh_matches_a_direct_product():
    robot = custom(PUMA, tool=(10.0, -20.0, 30.0))
    q = np.random.default_rng(0).uniform(-np.pi, np.pi, (64, 6))
    truth = mdh_flange(q, np.radians(PUMA["alpha_deg"]), PUMA["a"], PUMA["d"], np.radians(PUMA["offset_deg"]))
    with torch.no_grad():
        poses = fk_poses(torch.as_tensor(q, dtype=DTYPE), nominal_geometry(robot)).numpy()
    np.testing.assert_allclose(poses[:, :3, :3], truth[:, :3, :3], rtol=0, atol=1e-12)
    np.testing.assert_allclose(poses[:, :3, 3], truth[:, :3, 3], rtol=0, atol=1e-9)
    marker = truth[:, :3, :3] @ [10.0, -20.0, 30.0] + truth[:, :3, 3]
    np.testing.assert_allclose(fk_numpy(np.degrees(q), robot), marker, rtol=0, atol=1e-9)


def test_ur5_written_in_modified_dh_is_the_ur5():
    ur5 = nominal_robot("ur5")
    mdh = custom({"alpha_deg": [0, 90, 0, 0, 90, -90], "a": [0, 0, -425.0, -392.25, 0, 0], "d": list(ur5.d),
                  "offset_deg": [0] * 6, "convention": "modified"})
    np.testing.assert_array_equal(mdh.a, ur5.a)
    np.testing.assert_allclose(mdh.alpha, ur5.alpha, rtol=0, atol=1e-15)
    q = np.random.default_rng(1).uniform(-360, 360, (64, 6))
    np.testing.assert_allclose(fk_numpy(q, mdh), fk_numpy(q, ur5), rtol=0, atol=1e-9)
    truth = mdh_flange(np.radians(q), np.radians([0, 90, 0, 0, 90, -90]), [0, 0, -425.0, -392.25, 0, 0],
                       ur5.d, np.zeros(6))
    np.testing.assert_allclose(fk_numpy(q, ur5), truth[:, :3, 3], rtol=0, atol=1e-9)


def test_standard_is_the_default_convention_and_bad_tables_are_refused():
    std = {"d": list(PUMA["d"]), "a": list(PUMA["a"]), "alpha_deg": list(PUMA["alpha_deg"]), "offset_deg": [0] * 6}
    np.testing.assert_array_equal(custom(std).a, custom({**std, "convention": "standard"}).a)
    np.testing.assert_array_equal(custom(std).a, PUMA["a"])
    with pytest.raises(ValueError, match=r"alpha_0 = 90°\) must be 0"):
        custom({**PUMA, "alpha_deg": [90, -90, 0, -90, 90, -90]})
    with pytest.raises(ValueError, match=r"a_0 = 50 mm\) and alpha_deg"):
        custom({**PUMA, "a": [50, 0, 431.8, 20.32, 0, 0]})
    with pytest.raises(ValueError, match=r"robot.dh.convention: 'craig'"):
        custom({**PUMA, "convention": "craig"})
    with pytest.raises(ValueError, match=r"robot.dh: unknown key\(s\) \['theta'\]"):
        custom({**std, "theta": [0] * 6})


def test_a_custom_robots_joint_limits_reach_its_urdf_and_the_path_command():
    """Review (2026-11-29): a custom robot had no place for its joints' speed and torque limits, so its URDF
    said velocity and effort 0 on every joint (a planner may read "cannot move") and path needed its own."""
    import pinocchio as pin
    from pipeline.lib.robot.kinematics import nominal_geometry
    from pipeline.lib.robot.urdf import to_urdf
    from pipeline.lib.runtime.pathsolve import joint_speeds
    speeds, torques = [120.0, 120.0, 180.0, 180.0, 180.0, 180.0], [150.0, 150.0, 28.0, 28.0, 28.0, 28.0]
    arm = custom({**PUMA, "velocity_deg_s": speeds, "effort_nm": torques})
    m = pin.buildModelFromXML(to_urdf(nominal_geometry(arm), arm))
    np.testing.assert_allclose(m.velocityLimit, np.radians(speeds), rtol=1e-12)
    np.testing.assert_allclose(m.effortLimit, torques, rtol=1e-12)
    np.testing.assert_allclose(joint_speeds(arm, None), speeds, rtol=1e-12)
    with pytest.raises(ValueError, match=r"set them, here or as robot.dh.velocity_deg_s"):
        joint_speeds(custom(PUMA), None)
    for bad in ([100.0] * 5, [100.0] * 5 + [0.0], [100.0] * 5 + [float("nan")], "fast"):
        with pytest.raises(ValueError, match=r"params.yaml robot.dh.velocity_deg_s: 6 numbers > 0"):
            custom({**PUMA, "velocity_deg_s": bad})


def test_a_bad_tool_a_table_beside_a_catalogue_arm_and_a_model_not_named_stop_naming_the_key():
    """A review (2026-12-06, evening): robot.tool_mm was only length-checked (NaN, inf, 1e300, true passed; "1"
    gave numpy's "could not convert"); robot.dh beside a catalogue model was ignored unseen, even "garbage";
    robot.model [ur5] gave TypeError: unhashable list; an integer of 400 digits in a custom table, its speed
    limits or robot.joint_limits_deg gave numpy's TypeError. Each is now a ValueError naming the key."""
    base = {"model": "ur5", "dh": None, "joint_limits_deg": None, "tcp": None, "tool_mm": [0.0, 0.0, 109.0]}
    huge = 10 ** 400
    for tool in ([float("nan"), 0.0, 0.0], [0.0, float("inf"), 0.0], [1e300, 0.0, 0.0], [0.0, 0.0, 2000.5],
                 [True, 0.0, 0.0], ["1", 0.0, 0.0], [huge, 0, 0], [0.0, 0.0], None):
        with pytest.raises(ValueError, match=r"^params.yaml robot.tool_mm: \[x, y, z\], 3 finite numbers in mm .*"
                                             r"within ±2000, got"):
            load_robot({**base, "tool_mm": tool})
    assert load_robot({**base, "tool_mm": [2000, -2000.0, 0]}).tool.tolist() == [2000.0, -2000.0, 0.0]
    ur5 = {"d": list(UR["ur5"][0]), "a": [0.0] * 6, "alpha_deg": [90, 0, 0, 90, -90, 0], "offset_deg": [0] * 6}
    for dh in ("garbage", ur5, {}):
        with pytest.raises(ValueError, match=r"^params.yaml robot.dh: only with robot.model: custom \(a ur5 has"):
            load_robot({**base, "dh": dh})
    for model in (["ur5"], {"ur5": None}, 5, None):
        with pytest.raises(ValueError, match=r"^params.yaml robot.model: one of \['ur10', .* or 'custom', got"):
            load_robot({**base, "model": model})
    for key, value in (("d", [huge] + [0.0] * 5), ("velocity_deg_s", [huge] * 6)):
        with pytest.raises(ValueError, match=rf"^params.yaml robot.dh.{key}: 6 "):
            custom({**PUMA, key: value})
    with pytest.raises(ValueError, match=r"^params.yaml robot.joint_limits_deg: null or 6 pairs"):
        load_robot({**base, "joint_limits_deg": [[-huge, 10]] * 6})
    params = load_params(Path(__file__).resolve().parents[1] / "params.yaml")   # the project's own robots pass:
    presets = sorted(p.stem for p in PRESETS.glob("*.yaml"))                  # a catalogue model, dh null
    assert len(presets) >= 4
    for p in [params] + [merged_params(n, params) for n in presets]:
        robot = load_robot(section(p, "robot"))
        assert robot.name in TABLES and p["robot"]["dh"] is None and np.abs(robot.tool).max() <= 2000

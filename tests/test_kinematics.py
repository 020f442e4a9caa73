"""Forward kinematics of the nominal UR5/UR10 at poses checked by hand."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import pipeline
from conftest import background
from pipeline.lib.robot import errormaps as E
from pipeline.lib.robot.kinematics import (DHChain, angular_jacobian, fk, fk_jacobian, fk_numpy, fk_pose_jacobian,
                                           flange_rotations, nominal_geometry)
from pipeline.lib.robot.robots import load_robot, nominal_robot

UR5 = nominal_robot("ur5")

# Worked by hand from the table d = 89.159, 0, 0, 109.15, 94.65, 82.3; a = 0, -425, -392.25, 0, 0, 0:
#  zero pose: x = a2 + a3, y = -(d4 + d6), z = d1 - d5
#  q2 = -90°: joints 2-4 rotate +90° about base y: a2 + a3 point up, d5 points along -x
#  q2 = q4 = -90°: arm straight up, d5 along +z
#  q1 = 90°: the zero pose turned 90° about z: (x, y) -> (-y, x)
HAND_CHECKED = [
    ([0, 0, 0, 0, 0, 0], [-817.25, -191.45, 89.159 - 94.65]),
    ([0, -90, 0, 0, 0, 0], [-94.65, -191.45, 89.159 + 817.25]),
    ([0, -90, 0, -90, 0, 0], [0.0, -191.45, 89.159 + 817.25 + 94.65]),
    ([90, 0, 0, 0, 0, 0], [191.45, -817.25, 89.159 - 94.65]),
]


@pytest.mark.parametrize("q_deg, expected", HAND_CHECKED)
def test_ur5_fk_hand_checked(q_deg, expected):
    np.testing.assert_allclose(fk_numpy(np.array([q_deg]), UR5)[0], expected, atol=1e-9)


def test_ur10_zero_pose():
    ur10 = nominal_robot("ur10")
    np.testing.assert_allclose(fk_numpy(np.zeros((1, 6)), ur10)[0],
                               [-612 - 572.3, -(163.941 + 92.2), 127.3 - 115.7], atol=1e-9)


def test_tool_offset_follows_the_flange():
    # zero pose: flange z axis is base -y, flange x is base -x (checked by hand: R = Rx(π/2)·Rx(π/2)·Rx(-π/2))
    tool = load_robot({"model": "ur5", "tool_mm": [0, 0, 100], "dh": None, "joint_limits_deg": None, "tcp": None})
    p0, p1 = fk_numpy(np.zeros((1, 6)), UR5)[0], fk_numpy(np.zeros((1, 6)), tool)[0]
    np.testing.assert_allclose(p1 - p0, [0, -100, 0], atol=1e-9)


def test_joint_six_does_not_move_the_flange_centre():
    q = np.array([[10, -60, 40, -80, 30, 0], [10, -60, 40, -80, 30, 123]], float)
    p = fk_numpy(q, UR5)
    np.testing.assert_allclose(p[0], p[1], atol=1e-9)


def test_chain_is_differentiable_in_joints_and_geometry():
    g = {k: v.clone().requires_grad_(True) for k, v in nominal_geometry(UR5).items()}
    q = torch.zeros(1, 6, dtype=torch.float64, requires_grad=True)
    fk(q, g)[0, 2].backward()
    # dz/dd1 = 1 exactly; z at zero pose does not depend on joint 1's angle
    assert g["d"].grad[0].item() == pytest.approx(1.0)
    assert q.grad[0, 0].item() == pytest.approx(0.0, abs=1e-12)
    chain = DHChain(nominal_geometry(UR5))
    assert not any(p.requires_grad for p in chain.parameters())


def test_custom_robot_and_bad_tables():
    custom = load_robot({"model": "custom", "dh": {"d": list(UR5.d), "a": list(UR5.a),
                                                    "alpha_deg": [90, 0, 0, 90, -90, 0], "offset_deg": [0] * 6},
                         "joint_limits_deg": None, "tcp": None, "tool_mm": [0, 0, 0]})
    np.testing.assert_allclose(fk_numpy(np.zeros((1, 6)), custom), fk_numpy(np.zeros((1, 6)), UR5))
    with pytest.raises(ValueError, match="unknown robot 'ur4'"):
        nominal_robot("ur4")
    with pytest.raises(ValueError, match=r"custom robot needs \['alpha_deg', 'offset_deg'\]"):
        load_robot({"model": "custom", "dh": {"d": [0] * 6, "a": [0] * 6}, "joint_limits_deg": None, "tcp": None,
                    "tool_mm": [0, 0, 0]})
    with pytest.raises(ValueError, match=r"robot: unknown key\(s\) \['tool'\]; missing key\(s\) \['tool_mm'\]"):
        load_robot({"model": "ur5", "dh": None, "joint_limits_deg": None, "tcp": None, "tool": [0, 0, 0]})


def test_joint_limits_and_a_custom_table_beyond_the_arm_are_refused_naming_the_key():
    """A review (2026-12-06): robot.joint_limits_deg of ±100000° let a waypoint 100 turns away become a movej
    (628 rad); inverted pairs were blamed on the input file's row; a NaN in a custom DH table gave every
    waypoint "residual nan". And a movej speed was checked against the fastest joint (a UR10's wrists,
    3.14 rad/s), where its base, which may lead the move, turns at 2.09; a custom robot without speed limits
    was not checked at all."""
    def robot(limits=None, model="ur5", **dh):
        table = {"d": list(UR5.d), "a": list(UR5.a), "alpha_deg": [90, 0, 0, 90, -90, 0], "offset_deg": [0] * 6, **dh}
        return load_robot({"model": model, "dh": table if model == "custom" else None, "joint_limits_deg": limits,
                           "tcp": None, "tool_mm": [0, 0, 0]})
    for bad, said in (([[-100000, 100000]] + [[-360, 360]] * 5, r"joint\(s\) \[1\] beyond the robot's own limits"),
                      ([[360, -360]] * 6, "min < max"), ([[0, float("nan")]] * 6, "min < max"),
                      ([[-10, 10]] * 5, "6 pairs"), ("wide", "6 pairs"), ([[-360, True]] + [[-10, 10]] * 5, "6 pairs")):
        with pytest.raises(ValueError, match=rf"^params.yaml robot.joint_limits_deg: .*{said}"):
            robot(bad)
    assert robot([[-180, 180]] * 6).limits_deg.tolist() == [[-180.0, 180.0]] * 6
    with pytest.raises(ValueError, match=r"^params.yaml robot.dh.d: 6 finite numbers"):
        robot(model="custom", d=[float("nan")] + list(UR5.d[1:]))
    ur10 = nominal_robot("ur10")
    with pytest.raises(ValueError, match=r"program.movej.vel: 3.1 rad/s, faster than the ur10's slowest joint \(2.094"):
        ur10.check_joint_speed(3.1, "program.movej.vel")
    ur10.check_joint_speed(2.09, "program.movej.vel")
    with pytest.raises(ValueError, match=r"plan.vel: the robot's joint speed limits are unknown .* robot.dh.velocity_deg_s"):
        robot(model="custom").check_joint_speed(0.5, "plan.vel")
    robot(model="custom", velocity_deg_s=[90] * 6).check_joint_speed(1.5, "plan.vel")


def test_geometric_jacobian_equals_autograd_with_every_error_term():
    g = nominal_geometry(load_robot({"model": "ur5", "tool_mm": [1.0, -2.0, 100.0], "dh": None, "joint_limits_deg": None, "tcp": None}))
    gen = torch.Generator().manual_seed(3)
    rigid = {k: v + 1e-2 * torch.randn(v.shape, generator=gen, dtype=torch.float64)
             if k not in ("compliance", "mass", "com") else v for k, v in g.items()}
    q = (torch.rand(8, 6, generator=gen, dtype=torch.float64) * 2 - 1) * 3
    p, J = fk_jacobian(q, rigid)
    torch.testing.assert_close(p, fk(q, rigid), rtol=0, atol=1e-12)
    for k in range(3):
        qk = q.clone().requires_grad_(True)
        (grad,) = torch.autograd.grad(fk(qk, rigid)[:, k].sum(), qk)
        torch.testing.assert_close(J[:, k], grad, rtol=0, atol=1e-9)        # J ~ 1e2-1e3 mm/rad
    # a compliant arm (UR-like 1e4 N·m/rad): the position is exact, the Jacobian leaves out only
    # compliance * dtau/dq, under 1 % of the whole
    elastic = {**rigid, "compliance": torch.full((6,), 1e-4, dtype=torch.float64)}
    p, J = fk_jacobian(q, elastic)
    torch.testing.assert_close(p, fk(q, elastic), rtol=0, atol=1e-12)
    assert (p - fk(q, rigid)).norm(dim=1).max() > 0.05                      # the sag is there
    qk = q.clone().requires_grad_(True)
    J_auto = torch.func.vmap(torch.func.jacrev(lambda x: fk(x[None], elastic)[0]))(qk.detach())
    assert (J - J_auto).norm() < 0.01 * J_auto.norm()
    # nominal UR5: joint 6 turns the tool (1, -2, 100) about the flange z axis, on a radius of √5 mm
    p, J = fk_jacobian(q, nominal_geometry(load_robot({"model": "ur5", "tool_mm": [1.0, -2.0, 100.0], "dh": None, "joint_limits_deg": None, "tcp": None})))
    torch.testing.assert_close(J[:, :, 5].norm(dim=1), torch.full((8,), 5 ** 0.5, dtype=torch.float64))


def test_one_fk_pass_gives_the_position_orientation_and_both_jacobians_to_the_bit():
    """fk_pose_jacobian (a pose solver's step: realtime.chord_step, solvers.physics_trial) gives what fk_jacobian,
    flange_rotations and angular_jacobian give, bit for bit, on an arm with every error term (base correction,
    compliance, angle maps), from one FK pass where the three calls take three."""
    g = nominal_geometry(load_robot({"model": "ur5", "tool_mm": [1.0, -2.0, 100.0], "dh": None, "joint_limits_deg": None, "tcp": None}))
    gen = torch.Generator().manual_seed(5)
    g = {k: v + 1e-2 * torch.randn(v.shape, generator=gen, dtype=torch.float64) if k not in ("mass", "com") else v
         for k, v in g.items()} | {"compliance": torch.full((6,), 1e-4, dtype=torch.float64)}
    g |= E.as_geometry({"amap_coef": 1e-4 * np.sin(np.arange(6 * 180) / 7.0).reshape(6, 180),
                        "amap_cover": np.ones((6, 360))})
    q = (torch.rand(16, 6, generator=gen, dtype=torch.float64) * 2 - 1) * 3
    p, J, R, Jw = fk_pose_jacobian(q, g)
    assert torch.equal(p, fk_jacobian(q, g)[0]) and torch.equal(J, fk_jacobian(q, g)[1])
    assert torch.equal(R, flange_rotations(q, g)) and torch.equal(Jw, angular_jacobian(q, g))
    assert (p - fk(q, {k: v for k, v in g.items() if not k.startswith("amap")})).norm(dim=1).max() > 1e-3   # the maps act


FK_HASH = """
import hashlib, os
import pipeline                       # first, as a stage imports it: its pins before numpy and torch load
import numpy as np, torch
from pipeline.lib.robot import kinematics as K
from pipeline.lib.robot.robots import nominal_robot
q = torch.as_tensor(np.random.default_rng(0).uniform(-3, 3, (719, 6)), dtype=K.DTYPE)
g = K.nominal_geometry(nominal_robot("ur5"))                   # not by way of sim.twin: 1 s less a process
with torch.no_grad():
    out = [K.link_frames(q, g), K.fk(q, g), K.fk_jacobian(q, g)[1], K.gravity_torques(q, g)]
print(hashlib.md5(b"".join(t.numpy().tobytes() for t in out)).hexdigest(), flush=True)
os._exit(0)                           # the interpreter's own ending: ~0.5 s a process, nothing to it here
"""


@pytest.mark.slow
def test_the_chain_gives_the_same_bits_in_every_process():
    """The defect: with MKL on two threads, the first FK of a process gave other last bits in about one
    process in six (up to 1e-9 mm), so a fresh clone's `dvc repro` could differ from dvc.lock; the package
    now runs MKL on one thread (pipeline/__init__.py). 16 processes must agree (before: 2 of 16 differed,
    twice in a row here)."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    env.pop("PYTHONHASHSEED", None)
    hashes = {subprocess.run([sys.executable, "-c", FK_HASH], env=env, capture_output=True, text=True,
                             check=True, preexec_fn=background).stdout for _ in range(16)}
    assert len(hashes) == 1, hashes


KERNELS_RUN = """
import ctypes, glob, os
import pipeline
import numpy as np, torch
from numpy._core._multiarray_umath import __cpu_features__ as npy
openblas = ctypes.CDLL(glob.glob(os.path.dirname(np.__file__) + ".libs/libscipy_openblas*")[0])
openblas.scipy_openblas_get_corename64_.restype = ctypes.c_char_p
print(torch.backends.cpu.get_cpu_capability(), npy["X86_V4"], npy["AVX512_ICL"], npy["AVX512_SPR"],
      openblas.scipy_openblas_get_corename64_().decode(), os.environ["MKL_CBWR"], os.environ["ONEDNN_MAX_CPU_ISA"])
"""


@pytest.mark.skipif(not pipeline.X86, reason="x86-64 kernels")
def test_the_numeric_libraries_run_the_same_kernels_on_every_x86_cpu():
    """The defect: each library picks its kernels by the CPU it finds, and their last bits differ, so a
    fresh clone's `dvc repro` on an AMD EPYC (AVX-512) gave other bytes than the dvc.lock made on a Xeon,
    every output from the frame stage on. Importing the package now pins the AVX2 kernels, which every
    x86-64 machine here has: torch's own (before: AVX512 on both), numpy's loops (before: X86_V4),
    OpenBLAS's (before: SkylakeX), MKL's reproducible AVX2 branch and oneDNN's."""
    env = {k: v for k, v in os.environ.items() if k not in pipeline.KERNEL_PINS}
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[1])
    out = subprocess.run([sys.executable, "-c", KERNELS_RUN], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["AVX2", "False", "False", "False", "Haswell", "AVX2,STRICT", "AVX2"]

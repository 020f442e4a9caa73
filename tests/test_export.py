"""Exports for the robot cell, read back by the libraries a cell uses: Pinocchio (URDF, UR
kinematics YAML) and onnxruntime (the model)."""
import json
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import torch
import yaml
from scipy.spatial.transform import Rotation

from pipeline.stages.export import rigid_equivalent, ur_yaml_poses, urdf_positions
from conftest import project_points, served_model
from pipeline.lib.learning.checkpoint import load_model, make_model
from pipeline.lib.learning.model import Ensemble, PhysicsOnly
from pipeline.lib.learning.onnx_model import OnnxModel, OnnxRealtime, export_controller, export_onnx
from pipeline.lib.learning.workspace import Workspace
from pipeline.lib.project.columns import JOINTS_DEG, THEORY
from pipeline.lib.project.config import load_params, read_json
from pipeline.lib.robot.kinematics import DTYPE, fk, fk_frames, fk_pose, nominal_geometry
from pipeline.lib.robot.robots import UR_JOINTS, load_robot, nominal_robot
from pipeline.lib.robot.urdf import base_transform, flange_residual, joint_origins, to_urdf, ur_kinematics
from pipeline.lib.runtime.realtime import Realtime
from pipeline.lib.runtime.solvers import lm_jacobian, lm_step, predict
from pipeline.lib.sim.twin import sample_poses

ROOT = Path(__file__).resolve().parents[1]
PARAMS = load_params(ROOT / "params.yaml")
UR5 = nominal_robot("ur5")


def calibrated_like() -> dict:
    """Nominal UR5 with errors of a real calibration in every group the URDF must carry."""
    g = nominal_geometry(UR5)
    rng = np.random.default_rng(0)
    t = lambda v: torch.as_tensor(v, dtype=DTYPE)
    return {**g, "d": g["d"] + t(rng.normal(0, 0.3, 6)), "a": g["a"] + t(rng.normal(0, 0.3, 6)),
            "alpha": g["alpha"] + t(rng.normal(0, 1e-3, 6)), "offset": t(rng.normal(0, 2e-3, 6)),
            "beta": t([0.0, 8e-4, -3e-4, 0.0, 0.0, 0.0]), "tool": t([1.5, -2.0, 40.0]),
            "base": t([2e-4, -1e-3, 5e-4, 0.3, -0.2, 0.1])}


def poses(n=300, seed=1) -> torch.Tensor:
    return torch.as_tensor(np.random.default_rng(seed).uniform(-np.pi, np.pi, (n, 6)), dtype=DTYPE)


def test_urdf_read_by_pinocchio_matches_the_chain_to_1e6_mm():
    g, q = calibrated_like(), poses()
    text = to_urdf(g, UR5)
    with torch.no_grad():
        p = fk(q, g).numpy()
    assert np.abs(urdf_positions(text, q.numpy()) - p).max() < 1e-6
    m = pin.buildModelFromXML(text)
    assert list(m.names)[1:] == UR_JOINTS
    np.testing.assert_allclose(m.lowerPositionLimit, -2 * np.pi)
    np.testing.assert_allclose(m.effortLimit, [150, 150, 150, 28, 28, 28])
    assert {"base_link", "flange", "tool0"} <= {f.name for f in m.frames}


def test_the_urdf_and_yaml_carry_the_probe_and_tcp_frames():
    """tool0 is the probe's frame (its rotation in the flange included) and each robot.tcp a link on the
    flange: read back by Pinocchio, against the chain's own poses (issue 34)."""
    from pipeline.stages.export import urdf_poses
    from pipeline.lib.robot.kinematics import TOOL_ROT, fk_pose
    g = {**calibrated_like(), TOOL_ROT: torch.tensor([0.01, -0.02, -1.5707], dtype=DTYPE)}
    tcp = {"torch": {"xyz_mm": [150.0, 0.0, 80.0], "rxyz_deg": [0.0, 30.0, 0.0]}}
    q = poses(50)
    text = to_urdf(g, UR5, tcp=tcp)
    with torch.no_grad():
        p, R = (v.numpy() for v in fk_pose(q, g))
        flange = fk_pose(q, {**g, "tool": torch.zeros(3, dtype=DTYPE), TOOL_ROT: torch.zeros(3, dtype=DTYPE)})
    p_u, R_u = urdf_poses(text, q.numpy())
    assert np.abs(p_u - p).max() < 1e-6 and np.abs(R_u - R).max() < 1e-12
    p_t, R_t = urdf_poses(text, q.numpy(), "tcp_torch")
    want = flange[0].numpy() + flange[1].numpy() @ np.array([150.0, 0.0, 80.0])
    assert np.abs(p_t - want).max() < 1e-6
    np.testing.assert_allclose(R_t, flange[1].numpy() @ Rotation.from_euler("y", 30, degrees=True).as_matrix(),
                               atol=1e-12)
    frames = yaml.safe_load(yaml.safe_dump(ur_kinematics(g, tcp)))["tool_frames"]
    assert set(frames) == {"marker", "torch"}
    e = frames["torch"]                                              # joint 6's frame -> the TCP, m and rpy
    c = joint_origins(g)[1] @ np.r_[150.0, 0.0, 80.0, 1.0]            # the flange transform after joint 6, then c
    np.testing.assert_allclose([e["x"], e["y"], e["z"]], c[:3] / 1000, atol=1e-12)
    for e in frames.values():                  # ur_pose: the same frame as set_tcp takes it (m, a rotation vector)
        np.testing.assert_allclose(e["ur_pose"][:3], [e["x"], e["y"], e["z"]], atol=1e-15)
        np.testing.assert_allclose(Rotation.from_rotvec(e["ur_pose"][3:]).as_matrix(),
                                   Rotation.from_euler("xyz", [e["roll"], e["pitch"], e["yaw"]]).as_matrix(), atol=1e-12)
    assert np.linalg.norm(frames["torch"]["ur_pose"][3:]) > 0.1   # 30° about y: rpy and a rotation vector differ


def test_a_custom_robots_chain_files_are_both_written_and_read_back_with_its_tcp_links():
    """Review (2026-11-29): for robot.model custom the stage wrote no ur_calibration.yaml, which dvc.yaml declares,
    so `dvc repro` failed there; and the tcp_<name> links the docs say are read back were not."""
    from pipeline.stages.export import chain_files
    dh = {k: v.tolist() for k, v in (("d", UR5.d), ("a", UR5.a))}
    custom = load_robot({"model": "custom", "tool_mm": [0.0, 0.0, 0.0], "joint_limits_deg": None, "tcp": None,
                         "dh": {**dh, "alpha_deg": np.degrees(UR5.alpha).tolist(), "offset_deg": [0.0] * 6}})
    g = calibrated_like()
    tcp = {"torch": {"xyz_mm": [150.0, 0.0, 80.0], "rxyz_deg": [10.0, -20.0, 30.0]}}
    files, checked = chain_files(g, custom, tcp, poses(40), Path("out"))
    assert sorted(map(str, files)) == ["out/models/calibrated.urdf", "out/models/ur_calibration.yaml"]
    assert checked["ur_yaml"]["max_deviation_mm"] < 1e-6 and "no Universal Robots arm" in checked["ur_yaml"]["robot"]
    link = checked["urdf"]["tcp"]["torch"]
    assert link["max_deviation_mm"] < 1e-6 and link["max_rotation_deviation_arcsec"] < 1e-3
    kin = yaml.safe_load(files[Path("out/models/ur_calibration.yaml")])
    assert list(kin["tool_frames"]) == ["marker", "torch"]
    bent = {"torch": {"xyz_mm": [150.0, 0.0, 80.0], "rxyz_deg": [10.0, -20.0, 31.0]}}      # a link 1 deg off
    text = to_urdf(g, custom, tcp=bent)
    from pipeline.stages.export import tcp_links
    assert 3500 < tcp_links(text, tcp, poses(10), g)["torch"]["max_rotation_deviation_arcsec"] < 3700
    # a review (2026-12-06): its joints' speeds and torques, not given, went into the URDF as 0 unsaid
    assert "written as 0" in checked["urdf"]["speed_and_torque_limits"]
    assert 'velocity="0.0"' in files[Path("out/models/calibrated.urdf")]
    assert "speed_and_torque_limits" not in chain_files(g, UR5, tcp, poses(5), Path("out"))[1]["urdf"]


def test_a_tcp_name_a_yaml_1_2_reader_takes_for_a_number_is_written_quoted():
    """A review (2026-12-06, evening): robot.tcp names 1e3, 0o17, -1e3 pass the name rule, and PyYAML (YAML 1.1)
    wrote them unquoted in ur_calibration.yaml's tool_frames, where a YAML 1.2 reader (ROS 2's yaml-cpp,
    ruamel.yaml) reads the numbers 1000.0, 15, -1000.0. Now both readers read the names; the default project's
    file (tcp x150) is byte for byte what PyYAML wrote."""
    from pipeline.stages.export import chain_files
    readers = [yaml.safe_load]                                              # YAML 1.1
    try:
        from ruamel.yaml import YAML                                        # YAML 1.2 (DVC's, where installed)
        readers.append(YAML(typ="safe", pure=True).load)
    except ImportError:
        pass
    names = ["1e3", "0o17", "-1e3", "1e-3", "0x1F", "123", "true", "null", "x150", "e3", "a-1"]
    files, _ = chain_files(calibrated_like(), UR5, {n: {"xyz_mm": [150.0, 0.0, 80.0]} for n in names}, poses(5),
                           Path("out"))
    text = files[Path("out/models/ur_calibration.yaml")]
    for read in readers:
        assert list(read(text)["tool_frames"]) == ["marker", *names]
    assert "\n  '1e3':\n" in text and "\n  '0o17':\n" in text and "\n  x150:\n" in text and "\n  e3:\n" in text
    tcp = PARAMS["robot"]["tcp"]
    files, _ = chain_files(calibrated_like(), UR5, tcp, poses(5), Path("out"))
    assert files[Path("out/models/ur_calibration.yaml")] == yaml.safe_dump(ur_kinematics(calibrated_like(), tcp),
                                                                            sort_keys=False)


def test_an_export_that_fails_leaves_every_file_of_the_run_before(in_trained_project, tmp_path, monkeypatch):
    """Review (2026-11-29): the URDF and the YAML were written before the graphs were made: a run that failed
    there (a disk full) left a new URDF beside the old run's graphs and export.json."""
    import shutil
    from pipeline.stages import export
    for f in ("data/interim/points.parquet", "data/interim/split.parquet", "reports/frame.json",
              "models/calibration.json", "models/parts.json", "models/boter.pt", "models/workspace.json"):
        (tmp_path / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(f, tmp_path / f)
    old = {f: f"an earlier run's {f}" for f in ("models/calibrated.urdf", "models/ur_calibration.yaml",
                                                 "models/model.onnx", "reports/export.json")}
    for f, text in old.items():
        (tmp_path / f).write_text(text)

    def disk_full(model, paths):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(export, "export_all", disk_full)
    params = {**in_trained_project, "robot": {**in_trained_project["robot"],
                                              "tcp": {"torch": {"xyz_mm": [150.0, 0.0, 80.0]}}}}
    with pytest.raises(OSError, match="No space left"):
        export.run(params, tmp_path)
    assert {f: (tmp_path / f).read_text() for f in old} == old


@pytest.mark.parametrize("network", [True, False])
def test_the_export_is_the_model_evaluate_chose_to_serve(in_trained_project, tmp_path, monkeypatch, network):
    """The defect: the export stage exported the whole model where evaluate had left the network out
    (workspace.json network: false): model.onnx and the controller graphs answered with a network the
    pipeline reports, and the service serves, without. Each graph is now made from model.served."""
    import shutil
    from pipeline.stages import export
    for f in ("data/interim/points.parquet", "data/interim/split.parquet", "reports/frame.json",
              "models/calibration.json", "models/parts.json", "models/boter.pt", "models/workspace.json"):
        (tmp_path / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(f, tmp_path / f)
    ws = json.loads((tmp_path / "models/workspace.json").read_text())
    (tmp_path / "models/workspace.json").write_text(json.dumps({**ws, "network": network}))
    exported = []

    def stop_after(model, paths):
        exported.append(model)
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(export, "export_all", stop_after)
    with pytest.raises(OSError):
        export.run(in_trained_project, tmp_path)
    assert isinstance(exported[0], PhysicsOnly) != network


def test_nominal_ur5_at_zero_is_where_the_datasheet_puts_it():
    """Hand-checked: at q = 0 the UR5's flange is at x = a2 + a3, y = -(d4 + d6), z = d1 - d5 (m)."""
    text = to_urdf(nominal_geometry(UR5), UR5)
    np.testing.assert_allclose(urdf_positions(text, np.zeros((1, 6)))[0] / 1000,
                               [-0.425 - 0.39225, -(0.10915 + 0.0823), 0.089159 - 0.09465], atol=1e-12)


def test_ur_yaml_of_the_nominal_ur5_is_the_ur_descriptions_default():
    """The UR ROS description's default_kinematics.yaml for the UR5 (published values), compared as
    transforms (an rpy triple is not unique: wrist_3's (pi/2, pi, pi) is Rx(-pi/2))."""
    published = {"shoulder": ([0, 0, 0.089159], [0, 0, 0]),
                 "upper_arm": ([0, 0, 0], [np.pi / 2, 0, 0]),
                 "forearm": ([-0.425, 0, 0], [0, 0, 0]),
                 "wrist_1": ([-0.39225, 0, 0.10915], [0, 0, 0]),
                 "wrist_2": ([0, -0.09465, 0], [np.pi / 2, 0, 0]),
                 "wrist_3": ([0, 0.0823, 0], [np.pi / 2, np.pi, np.pi])}
    kin = ur_kinematics(nominal_geometry(UR5))["kinematics"]
    assert list(kin) == [*published, "hash"]          # ur_description's ur_common.xacro reads every one
    assert kin["hash"].startswith("spi_boter_") and kin["hash"] == ur_kinematics(nominal_geometry(UR5))["kinematics"]["hash"]
    assert kin["hash"] != ur_kinematics(calibrated_like())["kinematics"]["hash"]
    for name, (xyz, rpy) in published.items():
        e = kin[name]
        np.testing.assert_allclose([e["x"], e["y"], e["z"]], xyz, atol=1e-12, err_msg=name)
        R = Rotation.from_euler("xyz", [e["roll"], e["pitch"], e["yaw"]]).as_matrix()
        np.testing.assert_allclose(R, Rotation.from_euler("xyz", rpy).as_matrix(), atol=1e-9, err_msg=name)


def test_ur_yaml_chain_built_in_pinocchio_is_the_calibrated_chain_up_to_joint_6():
    g, q = calibrated_like(), poses(100)
    kin = yaml.safe_load(yaml.safe_dump(ur_kinematics(g)))           # through the file format
    with torch.no_grad():
        flange = fk_frames(q, g)[-1].numpy()
    truth = base_transform(g) @ flange @ np.linalg.inv(joint_origins(g)[1])
    got = ur_yaml_poses(kin, q.numpy())
    assert np.abs(got[:, :3, 3] - truth[:, :3, 3]).max() < 1e-6
    assert np.abs(got[:, :3, :3] - truth[:, :3, :3]).max() < 1e-12
    # what it leaves out: the flange transform after joint 6 (a6 only here: alpha6 and beta6 rotate)
    assert flange_residual(g)["translation_mm"] == pytest.approx(abs(float(g["a"][5])), abs=1e-12)


def test_a_calibration_with_joint_compliance_exports_its_best_rigid_chain():
    """A URDF cannot sag under gravity: the exported chain is fitted to the elastic model's positions,
    much closer to it than the elastic calibration's rigid part alone."""
    g = {**calibrated_like(), "compliance": torch.as_tensor([0, 1e-4, 2e-4, 8e-4, 8e-4, 0], dtype=DTYPE)}
    q = torch.as_tensor(np.radians(sample_poses(400, np.random.default_rng(2))), dtype=DTYPE)   # a campaign's
    rigid, fit = rigid_equivalent(g, q, PARAMS["calibrate"])
    assert not rigid["compliance"].any()
    with torch.no_grad():
        part = (fk(q, {**g, "compliance": torch.zeros(6, dtype=DTYPE)}) - fk(q, g)).norm(dim=1).numpy()
    assert fit["mean_mm"] < part.mean() / 5
    _, none = rigid_equivalent(calibrated_like(), q, PARAMS["calibrate"])    # rigid already: itself
    assert none == {"mean_mm": 0.0, "max_mm": 0.0, "left_out": []}
    # review (2026-11-29): a custom robot's load maps (no link masses: every step 0) act on nothing, yet were
    # listed as left out of the URDF
    t = lambda v: torch.as_tensor(v, dtype=DTYPE)                             # noqa: E731
    idle = {**calibrated_like(), "lmap_coef": t(np.full((6, 11), 1e-4)), "lmap_lo": t(np.zeros(6)),
            "lmap_step": t(np.zeros(6))}
    _, fit = rigid_equivalent(idle, q, PARAMS["calibrate"])
    assert fit == {"mean_mm": 0.0, "max_mm": 0.0, "left_out": []}
    acting = {**idle, "lmap_lo": t(np.full(6, -50.0)), "lmap_step": t(np.full(6, 12.5))}
    assert rigid_equivalent(acting, q[:50], PARAMS["calibrate"])[1]["left_out"] == ["per-joint load error maps"]


def small_boter(seed=0):
    cfg = {**PARAMS["model"], "d_model": 12, "n_head": 3, "n_layer": 1, "d_hidden": 16, "init_seed": seed}
    m = make_model(cfg, calibrated_like())
    m.fade.fit(np.degrees(poses(50, seed=3).numpy()), 40.0)           # some poses fade, some do not
    return m.eval()


def without_fade(model):
    model.fade.fade_to = None                                       # model.fade_to: null, a documented setting
    return model


@pytest.mark.parametrize("kind", ["boter", "ensemble", "no fade"])
def test_onnx_read_by_onnxruntime_matches_pytorch(tmp_path, kind):
    """No fade (model.fade_to: null): the defect, Fade's ones sized by len(q) fixed the graph's batch at 4."""
    model = {"boter": small_boter, "ensemble": lambda: Ensemble([small_boter(0), small_boter(1)]).eval(),
             "no fade": lambda: without_fade(small_boter())}[kind]()
    path = tmp_path / "model.onnx"
    export_onnx(model, path)
    import onnx
    graph = onnx.load(str(path)).graph
    assert [i.name for i in graph.input] == ["q_rad"] and [o.name for o in graph.output] == ["p_mm", "probe_rot"]
    assert b"onnx_model.py" not in path.read_bytes()                # no source paths (stack traces): issue 21
    assert not any(n.metadata_props or n.doc_string for n in graph.node)
    ort = OnnxModel(path)
    for n in (1, 7, 300):                                           # the batch size is free
        q = poses(n, seed=n).float()
        with torch.no_grad():
            ref = model(q.double())[0].numpy()
        out = ort(q.numpy())
        assert out.shape == (n, 3)
        assert np.abs(out - ref).max() < 1e-6, n
        R = ort.pose(q.numpy())[1]                                  # the probe's orientation (issue 34)
        with torch.no_grad():
            R_ref = fk_pose(q.double(), model.physics.geometry())[1].numpy()
        assert R.shape == (n, 3, 3) and np.abs(R - R_ref).max() < 1e-12, n


def test_export_stage_files_read_back(in_trained_project):
    """The export stage's files (after dvc repro, or conftest's small project): every file read back
    within its stated tolerance, the URDF loaded from disk by Pinocchio."""
    r = json.loads(Path("reports/export.json").read_text())
    assert r["urdf"]["max_deviation_mm"] < 1e-6 and r["ur_yaml"]["max_deviation_mm"] < 1e-6
    assert r["onnx"]["max_deviation_mm"] < 1e-6 and r["onnx"]["n_test_poses"] > 0
    assert pin.buildModelFromUrdf("models/calibrated.urdf").nq == 6
    kin = yaml.safe_load(Path("models/ur_calibration.yaml").read_text())["kinematics"]
    assert list(kin) == ["shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3", "hash"]
    assert all(isinstance(kin[j][k], float) for j in list(kin)[:6] for k in ("x", "y", "z", "roll", "pitch", "yaw"))
    assert isinstance(kin["hash"], str)          # ur_common.xacro: ${sec_kinematics['hash']}, no default
    assert OnnxModel("models/model.onnx")(np.zeros((2, 6))).shape == (2, 3)


def test_the_urdfs_tool_links_are_as_far_from_the_model_as_export_json_says(in_trained_project):
    """export.json's rigid_fit named the URDF's distance from the calibrated model at the marker only (0.25 mm
    mean on the twin), which robot-cell.md gave as what a planner using the URDF gets; at a tool 150 mm out,
    where the rigid chain's orientation error shows, it is more (a review: 0.32 mm mean, 1.4 max). Now
    rigid_fit has each tool's too: here recomputed with Pinocchio on the URDF's tcp_<name> link against the
    calibrated physics at that tool, every pose of the campaign."""
    from pipeline.lib.project.artifacts import load_points
    from pipeline.lib.robot.geometry import Calibration, with_parts
    from pipeline.lib.robot.kinematics import TOOL_ROT, fk_pose
    from pipeline.lib.robot.tcp import in_flange
    from pipeline.stages.export import urdf_poses
    fit = json.loads(Path("reports/export.json").read_text())["rigid_fit"]
    q = np.radians(load_points(Path("."))[JOINTS_DEG].to_numpy())
    g = with_parts(Calibration.from_dict(json.loads(Path("models/calibration.json").read_text())).geometry,
                   json.loads(Path("models/parts.json").read_text()))
    tcp = in_flange(load_params()["robot"]["tcp"], g)
    assert set(fit["tcp"]) == set(tcp) and TOOL_ROT in g
    for name, c in tcp.items():
        p_urdf, R_urdf = urdf_poses(Path("models/calibrated.urdf").read_text(), q, f"tcp_{name}")
        at = {**g, "tool": torch.as_tensor(c["xyz_mm"], dtype=DTYPE),
              TOOL_ROT: torch.as_tensor(np.radians(c.get("rxyz_deg", [0.0, 0.0, 0.0])), dtype=DTYPE)}
        with torch.no_grad():
            p_model = fk_pose(torch.as_tensor(q, dtype=DTYPE), at)[0].numpy()
        e = np.linalg.norm(p_urdf - p_model, axis=1)
        assert abs(e.mean() - fit["tcp"][name]["mean_mm"]) < 1e-9 and abs(e.max() - fit["tcp"][name]["max_mm"]) < 1e-9
        assert e.mean() > fit["mean_mm"]                    # the tool 150 mm out: further than the marker
    assert fit["orientation_arcsec"]["mean"] > 10


# The controller path as one graph (issue 24): models/controller.onnx, run by OnnxRealtime
def assert_same_answers(a: list, b: list) -> None:
    """Two controller paths' Results, pose by pose: angles to 1e-9 rad, residuals to 1e-6 mm, the same flags."""
    assert len(a) == len(b)
    for i, (x, y) in enumerate(zip(a, b)):
        assert np.abs(x.q - y.q).max() < 1e-9, (i, x.q - y.q)
        assert (x.residual_mm == y.residual_mm == np.inf) or abs(x.residual_mm - y.residual_mm) < 1e-6, (i, x, y)
        assert (x.verified, x.converged, x.in_workspace) == (y.verified, y.converged, y.in_workspace), (i, x, y)


def controller_cases(model, params) -> tuple[np.ndarray, np.ndarray]:
    """Start angles (n, 6) rad and targets (n, 3) mm: the test points towards their theory positions (as the
    compensate stage), the same angles 0.02 mm from the model's position there (verified in one step), far
    from the training poses (outside the workspace), and the origin (out of reach: not converged)."""
    df = project_points(params)
    test = df[df.split == "test"]
    q0, theory = np.radians(test[JOINTS_DEG].to_numpy()), test[THEORY].to_numpy()
    far = q0[:5] + np.radians([70.0, 0, 0, 0, 0, 0])
    with torch.no_grad():
        at = lambda q: model(torch.as_tensor(q))[0].numpy()
        near, off = at(q0) + [0.012, -0.01, 0.0115], at(far) + [0.3, 0.0, -0.2]
    return np.vstack([q0, q0, far, q0[:1]]), np.vstack([theory, near, off, [[0.0, 0.0, 0.0]]])


def test_controller_onnx_answers_as_the_pytorch_controller_path(in_trained_project):
    """The export stage's models/controller.onnx on onnxruntime (OnnxRealtime) answers every case as the PyTorch
    controller path (Realtime) does, one pose per call and all in one batch, with the robot's joint limits and
    with limits that bind; its inputs and outputs as documented (docs/robot-cell.md)."""
    import onnx
    graph = onnx.load("models/controller.onnx").graph
    assert [i.name for i in graph.input] == ["q0_rad", "target_mm", "q_min_rad", "q_max_rad", "damping"]
    assert [o.name for o in graph.output] == ["q1_rad", "q2_rad", "r0_mm", "r1_mm"]
    double = onnx.TensorProto.DOUBLE
    assert all(v.type.tensor_type.elem_type == double for v in [*graph.input, *graph.output])
    batch = graph.input[0].type.tensor_type.shape.dim[0].dim_param               # the batch size is free
    assert batch and [d.dim_param for d in graph.input[4].type.tensor_type.shape.dim] == [batch]   # damping (batch,)
    assert [len(o.type.tensor_type.shape.dim) for o in graph.output] == [2, 2, 1, 1]
    params = in_trained_project
    model, ws = served_model(), Workspace.from_dict(read_json("models/workspace.json"))
    limits, tol = np.radians(load_robot(params["robot"]).limits_deg), params["compensate"]["tol_mm"]
    q0, tgt = controller_cases(model, params)
    torch_rt, onnx_rt = Realtime(model, limits, tol, workspace=ws), OnnxRealtime("models/controller.onnx", limits,
                                                                                  tol, ws)
    single = [onnx_rt(a, b) for a, b in zip(q0, tgt)]
    assert_same_answers(single, [torch_rt(a, b) for a, b in zip(q0, tgt)])
    assert_same_answers(onnx_rt.batch(q0, tgt), torch_rt.batch(q0, tgt))
    flags = lambda k: {getattr(r, k) for r in single}
    assert flags("verified") == flags("converged") == flags("in_workspace") == {True, False}   # every kind occurs
    tight = np.stack([q0[:3] - np.radians(0.01), q0[:3] + np.radians(0.01)], -1)   # (3, 6, 2): ±0.01°
    for lim, a, b in zip(tight, q0[:3], tgt[:3]):                                  # the clamps bind
        x, y = OnnxRealtime("models/controller.onnx", lim, tol)(a, b), Realtime(model, lim, tol)(a, b)
        assert_same_answers([x], [y])
        assert np.abs(x.q - a).max() <= np.radians(0.01) + 1e-12 and not x.converged


def test_a_nan_in_a_batch_is_that_rows_failure_not_the_batchs(in_trained_project):
    """Review (2026-11-29): one NaN angle or target in a batch made every graph fail (onnxruntime: GatherND
    index -2^63, the load maps' knot index of a NaN torque) and the PyTorch path raise IndexError: the whole
    batch lost. Now that row's answer is NaN, not converged; the others are what they are alone."""
    params = in_trained_project
    model, ws = served_model(), Workspace.from_dict(read_json("models/workspace.json"))
    limits, tol = np.radians(load_robot(params["robot"]).limits_deg), params["compensate"]["tol_mm"]
    q0, tgt = (a[:4].copy() for a in controller_cases(model, params))
    q0[1, 2], tgt[2, 0] = np.nan, np.nan
    for rt in (Realtime(model, limits, tol, workspace=ws), OnnxRealtime("models/controller.onnx", limits, tol, ws)):
        got = rt.batch(q0, tgt)
        assert [r.converged for r in got[1:3]] == [False, False] and not got[1].in_workspace
        assert_same_answers([got[0], got[3]], [rt(q0[0], tgt[0]), rt(q0[3], tgt[3])])
    p = OnnxModel("models/model.onnx")(q0.astype(np.float32))
    assert np.isnan(p[1]).all() and np.isfinite(p[[0, 2, 3]]).all()


def test_lm_step_on_the_controller_graph_is_lm_in_pytorch(in_trained_project):
    """OnnxRealtime.lm_step (one graph run, its first step damped by each row's λ) against solvers.lm_step
    with the DH branch's Jacobian, from the same state at each of 12 iterations of far starts, λ per row
    from 1e-3 to 1e2: the same steps kept (the same λ after) while above the tolerance (within it, a step
    changes |r| by its rounding), angles to 2e-9 rad, |r| to 1e-6 mm (the float32 network's rounding;
    iterated apart, the two drift to ~1e-7 rad)."""
    params = in_trained_project
    model = served_model()
    limits = np.radians(load_robot(params["robot"]).limits_deg)
    q0, tgt = controller_cases(model, params)
    q0 = np.roll(q0, 5, axis=0)                                                    # starts far from the targets
    g = OnnxRealtime("models/controller.onnx", limits)
    jac, lim = lm_jacobian(model, "physics"), torch.as_tensor(limits, dtype=DTYPE)
    q, t, lam = torch.as_tensor(q0, dtype=DTYPE), torch.as_tensor(tgt, dtype=DTYPE), torch.logspace(-3, 2, len(q0))
    with torch.no_grad():
        r = predict(model, q) - t
    err, kept = r.norm(dim=1), []
    for _ in range(12):
        qg, eg, lg = g.lm_step(q.numpy(), tgt, err.numpy(), lam.numpy())
        q2, r, err2, lam2 = lm_step(model, jac, q, r, err, lam, t, lim)
        away = (err > 1e-3).numpy()
        assert away.any() and np.array_equal(lg[away], lam2.numpy()[away])
        assert np.abs(qg - q2.numpy()).max() < 2e-9 and np.abs(eg - err2.numpy()).max() < 1e-6
        kept.append(lam2 < lam)
        q, err, lam = q2, err2, lam2
    kept = torch.stack(kept)
    assert kept.any() and not kept.all() and (err < 1e-3).any()                   # steps kept, refused; some converge


def test_controller_onnx_is_the_same_bytes_when_exported_again(in_trained_project, tmp_path):
    """DVC outputs: exported again (another process, another directory), the same file, with no source paths.
    (controller_physics.onnx, written by the same function, is held to its bytes by the record of the repro in
    test_pipeline_e2e.py, as every output is; exporting it here too cost the suite ~17 s. Where the model is
    served without its network, it is the graph exported here.)"""
    export_controller(served_model(), tmp_path / "controller.onnx")
    data = (tmp_path / "controller.onnx").read_bytes()
    assert data == Path("models/controller.onnx").read_bytes()
    network = Workspace.from_dict(read_json("models/workspace.json")).network
    physics = Path("models/controller_physics.onnx").read_bytes()       # served without its network, the model is
    assert (physics == data) != network                                 # its physics: export_all copies the graph
    assert b"realtime.py" not in data and b"onnx_model.py" not in data
    export = json.loads(Path("reports/export.json").read_text())
    for name in ("controller", "controller_physics"):          # the export stage's read-back of both
        r = export[name]
        assert r["max_q_rad"] < 1e-9 and r["max_residual_mm"] < 1e-6 and r["flags_differ"] == 0


def test_the_physics_controller_answers_as_the_model_where_its_network_has_faded(in_trained_project):
    """models/controller_physics.onnx (the controller path on the model's physics branch alone,
    model.PhysicsOnly) answers every case as the PyTorch path on PhysicsOnly, alone and batched. Far from
    the training poses, where the network's correction has faded to 0 at both evaluations, its answers are
    the whole model's (models/controller.onnx); at the test poses they are not (the network's correction)."""
    params = in_trained_project
    model, ws = load_model("models/boter.pt"), Workspace.from_dict(read_json("models/workspace.json"))
    limits, tol = np.radians(load_robot(params["robot"]).limits_deg), params["compensate"]["tol_mm"]
    q0, tgt = controller_cases(model, params)
    physics = OnnxRealtime("models/controller_physics.onnx", limits, tol, ws)
    in_torch = Realtime(PhysicsOnly(model), limits, tol, workspace=ws)
    single = [physics(a, b) for a, b in zip(q0, tgt)]
    assert_same_answers(single, [in_torch(a, b) for a, b in zip(q0, tgt)])
    assert_same_answers(physics.batch(q0, tgt), in_torch.batch(q0, tgt))
    whole = OnnxRealtime("models/controller.onnx", limits, tol, ws)
    test = len(q0) // 2 - 3                                      # controller_cases: the test poses come first
    gaps = [np.abs(a.q - b.q).max() for a, b in zip(single[:test], whole.batch(q0[:test], tgt[:test]))]
    if ws.network:                                               # at the test poses: the network's correction
        assert min(gaps) > 0 and max(gaps) > 1e-6
    else:                                                        # left out by evaluate: the whole model's graph
        assert max(gaps) == 0                                    # is the physics' (export: model.served)
    q = poses(60, seed=11).numpy()                               # random poses, most far from the training ones
    with torch.no_grad():
        t = model(torch.as_tensor(q))[0].numpy() + [0.3, 0.0, -0.2]
        q1 = physics.solve(q, t)[0]
        faded = ((model.fade(torch.as_tensor(q)) == 0) & (model.fade(torch.as_tensor(q1)) == 0))[:, 0].numpy()
    assert 10 <= faded.sum() < len(q)
    for a, b, f in zip(physics.batch(q, t), whole.batch(q, t), faded):
        gap = np.abs(a.q - b.q).max()
        assert gap < 1e-12 if f or not ws.network else gap > 0     # no network served: one graph, everywhere


def test_controller_onnx_of_an_ensemble_answers_as_realtime(tmp_path):
    model = Ensemble([small_boter(0), small_boter(1)]).eval()
    export_controller(model, tmp_path / "controller.onnx")
    q0 = poses(30, seed=5).numpy()
    with torch.no_grad():
        tgt = model(torch.as_tensor(q0))[0].numpy() + [0.2, -0.1, 0.1]
    onnx_rt, torch_rt = OnnxRealtime(tmp_path / "controller.onnx"), Realtime(model)
    assert_same_answers([onnx_rt(a, b) for a, b in zip(q0, tgt)], [torch_rt(a, b) for a, b in zip(q0, tgt)])
    assert_same_answers(onnx_rt.batch(q0, tgt), torch_rt.batch(q0, tgt))


def test_the_marker_graph_is_the_tcp_graph_at_the_probe_to_the_bit(in_trained_project, tmp_path):
    """The export stage traces the controller path once for two files: models/controller_tcp.onnx, and
    models/controller.onnx, that graph with tcp_mm fixed at the probe offset (at_probe). The marker's graph
    must take no TCP and answer as the path traced without one (two_steps with no tcp_mm), to the bit; the
    TCP graph fed the probe offset too, and another offset otherwise."""
    import onnx
    from pipeline.lib.learning.onnx_model import CONTROLLER_INPUTS, CONTROLLER_OUTPUTS, _export, save
    from pipeline.lib.runtime.realtime import two_steps

    class Marker(torch.nn.Module):                                   # the path as traced before at_probe
        def __init__(self, model):
            super().__init__()
            self.model = model

        def forward(self, q0_rad, target_mm, q_min_rad, q_max_rad, damping):
            return two_steps(self.model, q0_rad, target_mm, q_min_rad, q_max_rad, damping)

    model = served_model()
    for p in model.parameters():
        p.requires_grad_(False)
    args = (torch.zeros(4, 6, dtype=DTYPE), torch.zeros(4, 3, dtype=DTYPE), torch.full((6,), -np.pi, dtype=DTYPE),
            torch.full((6,), np.pi, dtype=DTYPE), torch.full((4,), 1e-9, dtype=DTYPE))
    save(_export(Marker(model), args, list(CONTROLLER_INPUTS), list(CONTROLLER_OUTPUTS),
                 ({0: "batch"}, {0: "batch"}, None, None, {0: "batch"})), tmp_path / "traced.onnx")
    assert [i.name for i in onnx.load("models/controller.onnx").graph.input] == list(CONTROLLER_INPUTS)
    q0 = poses(40, seed=8).numpy()
    with torch.no_grad():
        tgt = model(torch.as_tensor(q0))[0].numpy() + np.random.default_rng(8).normal(0, 0.5, (40, 3))
    tool = model.physics.geometry()["tool"].numpy()
    want = OnnxRealtime(tmp_path / "traced.onnx").solve(q0, tgt)
    for got in (OnnxRealtime("models/controller.onnx").solve(q0, tgt),
                OnnxRealtime("models/controller_tcp.onnx", tcp_mm=tool).solve(q0, tgt)):
        assert all(np.array_equal(a, b) for a, b in zip(got, want))
    assert not np.array_equal(OnnxRealtime("models/controller_tcp.onnx", tcp_mm=tool + [0.0, 0.0, 1.0]).solve(q0, tgt)[0],
                              want[0])                                # the TCP input acts


def test_the_tcp_controller_graph_answers_for_any_tool_as_the_pytorch_path_at_it(in_trained_project):
    """Issue 34: models/controller_tcp.onnx takes the TCP (flange frame) as an input; fed robot.tcp's x150, and
    a tool the export never saw, it answers every case as the PyTorch controller path on tcp.AtTcp, alone and
    in a batch, and the answers put that TCP, not the marker, on the target. The marker's own graph refuses
    a tool (its inputs do not take one), and the TCP graph refuses to run without one."""
    import onnx
    from pipeline.lib.robot.tcp import AtTcp, probe_offsets
    graph = onnx.load("models/controller_tcp.onnx").graph
    assert [i.name for i in graph.input] == ["q0_rad", "target_mm", "q_min_rad", "q_max_rad", "damping", "tcp_mm"]
    params = in_trained_project
    model, ws = served_model(), Workspace.from_dict(read_json("models/workspace.json"))
    limits, tol = np.radians(load_robot(params["robot"]).limits_deg), params["compensate"]["tol_mm"]
    q0 = controller_cases(model, params)[0][:40]
    for xyz in (params["robot"]["tcp"]["x150"]["xyz_mm"], [20.0, -80.0, 240.0]):
        at = AtTcp(model, probe_offsets({"t": {"xyz_mm": xyz}}, model.physics.geometry())["t"])
        with torch.no_grad():
            tgt = at(torch.as_tensor(q0))[0].numpy() + [0.3, -0.2, 0.25]          # 0.45 mm from each pose's TCP
        fast = OnnxRealtime("models/controller_tcp.onnx", limits, tol, ws, tcp_mm=xyz)
        slow = Realtime(at, limits, tol, workspace=ws)
        single = [fast(a, b) for a, b in zip(q0, tgt)]
        assert_same_answers(single, [slow(a, b) for a, b in zip(q0, tgt)])
        assert_same_answers(fast.batch(q0, tgt), slow.batch(q0, tgt))
        with torch.no_grad():
            landed = at(torch.as_tensor(np.array([r.q for r in single])))[0].numpy()
        ok = np.array([r.converged for r in single])
        assert ok.mean() > 0.9 and np.linalg.norm(landed - tgt, axis=1)[ok].max() < tol
    with pytest.raises(ValueError, match="not the controller path's"):
        OnnxRealtime("models/controller.onnx", limits, tcp_mm=[150.0, 0, 0])
    with pytest.raises(ValueError, match="not the controller path's"):
        OnnxRealtime("models/controller_tcp.onnx", limits)
    export = json.loads(Path("reports/export.json").read_text())
    for name in ("controller_tcp", "controller_physics_tcp"):  # the export stage's read-back at each robot.tcp
        r = export[name]["x150"]
        assert r["max_q_rad"] < 1e-9 and r["max_residual_mm"] < 1e-6 and r["flags_differ"] == 0


def test_the_pose_controller_graph_solves_six_equations_as_pytorch_does(in_trained_project):
    """Issue 34: models/controller_pose.onnx (two chord steps, six equations: a TCP's position and the flange's
    orientation, the 6×6 solve in closed form) answers as PyTorch's realtime.two_steps, one pose and a batch,
    at x150 and at the marker; from 0.05° off, its verified answers put the model's TCP within tol_mm and the
    flange (scipy, from the model's chain) within tol_arcsec of the target pose. Called as a controller
    (OnnxRealtime(...)(q, target, rot)), its answer; without rot, an error that says to give it."""
    import onnx
    from scipy.spatial.transform import Rotation
    from pipeline.lib.robot.kinematics import flange_rotations
    from pipeline.lib.runtime.realtime import DAMPING, two_steps
    from pipeline.lib.runtime.solvers import pose_weight
    from pipeline.lib.robot.tcp import AtTcp, probe_offsets
    graph = onnx.load("models/controller_pose.onnx").graph
    assert [i.name for i in graph.input] == ["q0_rad", "target_mm", "q_min_rad", "q_max_rad", "damping", "tcp_mm",
                                             "target_rot", "weight"]
    params = in_trained_project
    model = served_model().eval()
    limits = np.radians(load_robot(params["robot"]).limits_deg)
    tol, w = params["compensate"]["tol_mm"], pose_weight(params["compensate"])
    q_true = controller_cases(model, params)[0][:30]
    q0 = q_true + np.radians(np.random.default_rng(5).uniform(-0.05, 0.05, q_true.shape))
    g = model.physics.geometry()
    for xyz in (params["robot"]["tcp"]["x150"]["xyz_mm"], g["tool"].tolist()):
        at = AtTcp(model, probe_offsets({"t": {"xyz_mm": xyz}}, g)["t"])
        with torch.no_grad():
            target = at(torch.as_tensor(q_true))[0].numpy()
            rot = flange_rotations(torch.as_tensor(q_true), g).numpy()
        fast = OnnxRealtime("models/controller_pose.onnx", limits, tcp_mm=xyz, weight=w)
        got = fast.solve(q0, target, rot=rot)
        lo, hi = (torch.as_tensor(limits[:, i], dtype=DTYPE) for i in (0, 1))
        with torch.no_grad():
            want = [t.numpy() for t in two_steps(model, torch.as_tensor(q0), torch.as_tensor(target), lo, hi, DAMPING,
                                                 torch.as_tensor(xyz, dtype=DTYPE), torch.as_tensor(rot), w)]
        assert max(np.abs(a - b).max() for a, b in zip(got[:2], want[:2])) < 1e-9
        assert max(np.abs(a - b).max() for a, b in zip(got[2:], want[2:])) < 1e-6
        one = fast.solve(q0[:1], target[:1], rot=rot[:1])
        assert np.abs(one[0] - got[0][:1]).max() < 1e-12
        called = fast(q0[:1], target[:1], rot[:1])                                # OnnxRealtime's Result
        assert np.abs(called.q - np.where(got[3][0] < tol, got[0][0], got[1][0])).max() < 1e-12
        with pytest.raises(ValueError, match=r"a pose graph .* give rot"):        # was onnxruntime's "target_rot
            fast(q0[:1], target[:1])                                              # missing"
        assert (got[2] > 10 * tol).all()                                          # real work
        verified = got[3] < tol                                                   # q1, its residual measured
        converged = verified | (got[3] ** 2 / got[2] < tol)                      # else q2, predicted (answers())
        assert converged.mean() > 0.9
        q = np.where(verified[:, None], got[0], got[1])
        with torch.no_grad():
            landed = at(torch.as_tensor(q))[0].numpy()
            turned = flange_rotations(torch.as_tensor(q), g).numpy()
        miss = np.linalg.norm(landed - target, axis=1)
        off = np.degrees(Rotation.from_matrix(turned @ rot.transpose(0, 2, 1)).magnitude()) * 3600
        assert miss[verified].max(initial=0) < tol and miss[converged].max() < 2 * tol, miss
        assert off[converged].max() < 2 * params["compensate"]["tol_arcsec"], off
    r = json.loads(Path("reports/export.json").read_text())["controller_pose"]["x150"]
    assert r["max_q_rad"] < 1e-9 and r["max_residual_mm"] < 1e-6                 # the stage's own read-back


class _Patterns(torch.nn.Module):
    """A few shapes that onnxscript's pattern rules rewrite (a clamp as Max then Min, transposes and
    unsqueezes in a row, reshapes of a reshape) around a linear layer."""

    def __init__(self):
        super().__init__()
        self.lin = torch.nn.Linear(6, 4)

    def forward(self, q):                                        # (B, 6) -> (B, 4), (B, 4)
        h = self.lin(q.clamp(-1.0, 1.0))
        t = h.transpose(0, 1).transpose(0, 1).unsqueeze(0).unsqueeze(0)          # (1, 1, B, 4)
        return t.reshape(-1, 2).reshape(-1, 4), torch.relu(h).clamp(max=0.5)


def test_optimise_makes_the_exporters_graph_at_less_cost(tmp_path):
    """onnx_model.optimise (folding, the pattern rules on the folded graph, folding) gives the nodes of
    the exporter's own optimiser and onnxruntime's answers to the bit (docs/decisions.md: it is several
    times cheaper on the controller graphs)."""
    import onnx
    import onnxruntime as ort
    from pipeline.lib.learning.onnx_model import optimise, strip_annotations
    torch.manual_seed(0)
    m, q = _Patterns().eval(), torch.randn(5, 6)
    graphs = {}
    for ours in (False, True):
        program = torch.onnx.export(m, (q,), None, input_names=["q"], output_names=["a", "b"], dynamo=True,
                                    dynamic_shapes=({0: torch.export.Dim("batch")},), optimize=not ours)
        if ours:
            optimise(program.model)
        proto = program.model_proto
        strip_annotations(proto)
        onnx.save_model(proto, str(tmp_path / f"{ours}.onnx"))
        graphs[ours] = sorted(n.op_type for n in proto.graph.node)
    assert graphs[True] == graphs[False] and "Clip" in graphs[True] and "Transpose" not in graphs[True]
    x = np.random.default_rng(0).normal(size=(7, 6)).astype(np.float32)
    answers = [ort.InferenceSession(str(tmp_path / f"{ours}.onnx"), providers=["CPUExecutionProvider"])
               .run(None, {"q": x}) for ours in (False, True)]
    assert all(np.array_equal(a, b) for a, b in zip(*answers, strict=True))
    with torch.no_grad():
        assert np.allclose(answers[1][0], m(torch.as_tensor(x))[0].numpy(), atol=1e-6)


def test_a_model_file_whose_writing_fails_leaves_the_one_before(tmp_path, monkeypatch):
    """A checkpoint and an ONNX graph, the files the robot cell's commands load, are written whole or not at
    all: a save that fails halfway (a config that cannot be pickled; a disk full halfway through the graph)
    leaves the file that was there byte for byte, and no temporary file (before: the checkpoint was cut to
    a torch archive that does not load, the graph to its first 1000 bytes). Written again, the same bytes:
    the temporary folder keeps the file's name, which torch.save writes into the archive."""
    import onnx
    from pipeline.lib.learning.checkpoint import save_model
    cfg = {**PARAMS["model"], "d_model": 12, "n_head": 3, "n_layer": 1, "d_hidden": 16}   # small: written, not
    model = make_model(cfg, nominal_geometry(nominal_robot("ur5")))                       # traced, is the point
    path = tmp_path / "boter.pt"
    save_model(model, path, cfg)
    before = path.read_bytes()
    with pytest.raises(Exception):
        save_model(model, path, {**cfg, "unpicklable": lambda: 0})
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["boter.pt"]
    assert isinstance(load_model(path), type(model))
    save_model(model, path, cfg)
    assert path.read_bytes() == before
    from pipeline.lib.learning import onnx_model
    traced, trace = [], onnx_model._export                # one trace for both writings (~8 s less):
    monkeypatch.setattr(onnx_model, "_export",           # the second's writing is what is tested
                        lambda *a: traced[0] if traced else traced.append(trace(*a)) or traced[0])
    graph = tmp_path / "model.onnx"
    export_onnx(model, graph)
    first = graph.read_bytes()

    def disk_full(proto, where, **kw):                 # half the graph written, then the disk is full
        Path(where).write_bytes(proto.SerializeToString()[:1000])
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(onnx, "save_model", disk_full)
    with pytest.raises(OSError, match="No space left"):
        export_onnx(model, graph)
    assert graph.read_bytes() == first and sorted(p.name for p in tmp_path.iterdir()) == ["boter.pt", "model.onnx"]

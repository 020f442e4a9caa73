"""Stage export: the calibration into the robot cell (docs/data-format.md, "Exports for the robot cell").

    models/calibrated.urdf       the calibrated rigid chain (lib/robot/urdf.py), base_link .. flange, tool0
    models/ur_calibration.yaml   the UR ROS description's kinematics calibration (any robot's chain in its layout)
    models/model.onnx            the trained model as served (model.served: its physics branch alone where
                                 evaluate left the network out), q_rad -> p_mm (lib/learning/onnx_model.py);
                                 the controller graphs too
    models/controller.onnx       the controller path (lib/runtime/realtime.py: two chord steps) as one graph,
                                 q0_rad, target_mm, joint limits -> q1, q2, |r0|, |r1| (lib/learning/onnx_model.py)
    models/controller_physics.onnx   the same on the model's physics branch alone (model.PhysicsOnly:
                                 the calibration with its error maps, the network left out), for a
                                 controller whose cycle cannot hold the network
    models/controller_tcp.onnx, models/controller_physics_tcp.onnx   the same two with one more input,
                                 tcp_mm (3,): the targets are that TCP's (flange frame), not the marker's
                                 (traced once: the two above are these graphs with tcp_mm fixed at the
                                 probe offset, onnx_model.at_probe)
    models/controller_pose.onnx  the whole model's at a TCP for a pose: target_rot (the flange's orientation)
                                 and its weight too, six equations a step

and reports/export.json, what each file was checked against, by libraries the
pipeline does not use for its own kinematics:
    urdf   Pinocchio loads the URDF; its tool0, and each robot.tcp link, vs the pipeline's FK of the
           exported chain, every pose of the campaign
    yaml   the chain the UR description builds from the YAML (joint i's origin = entry i, axis z,
           tool0 on joint 6's frame), built in Pinocchio, vs the exported chain up to joint 6;
           the flange transform after joint 6 the format cannot hold is reported

A URDF has no joint compliance and no per-joint error maps. When the model's physics branch (the
calibration, with the parts stage's maps when they hold) has them, its rigid part alone is
millimetres off (the sag's mean is absorbed in the joint offsets), so the exported chain is the
rigid one that best reproduces that physics at the commanded angles (`rigid_equivalent`, least
squares over the campaign's poses); how far it stays from it, and what it leaves out, is
`rigid_fit` in export.json. The ONNX model carries every part.
    onnx   onnxruntime vs PyTorch on every test pose: on the same float32 angles, and on the
           float64 angles PyTorch is fed otherwise (the float32 input's rounding)
    controller  onnxruntime's answers (OnnxRealtime) vs the PyTorch controller path's (Realtime) on
           every test pose towards its theory position, one call each and all in one batch: the largest
           difference in angles (rad) and residual (mm), and answers whose flags differ
    controller_physics  the same for controller_physics.onnx against Realtime on PhysicsOnly(model)
    controller_tcp, controller_physics_tcp  the same at every `robot.tcp` point (each test pose towards
           that TCP's nominal position), against Realtime on tcp.AtTcp of the model (of PhysicsOnly(model));
           without robot.tcp, at a point 150 mm along the flange's x
    controller_pose  the same two steps for each test pose's nominal pose at each such TCP (its position and
           the flange's nominal orientation, weighted as compensate's lm weighs them), onnxruntime against
           PyTorch's realtime.two_steps: the largest difference in angles (rad) and |r| (mm)
"""
import tempfile
from pathlib import Path

import numpy as np
import pinocchio as pin
import torch
from scipy.spatial.transform import Rotation

from pipeline.lib.learning.checkpoint import load_model
from pipeline.lib.learning.model import PhysicsOnly, served
from pipeline.lib.learning.workspace import Workspace
from pipeline.lib.learning.onnx_model import OnnxModel, OnnxRealtime, deviation, export_all
from pipeline.lib.project.artifacts import (CALIBRATED_GEOMETRY, CONTROLLER_ONNX, CONTROLLER_PHYSICS_ONNX,
                                            CONTROLLER_PHYSICS_TCP_ONNX, CONTROLLER_POSE_ONNX, CONTROLLER_TCP_ONNX,
                                            EXPORT_JSON, FRAME_JSON, HERE, MODEL_ONNX, MODEL_WEIGHTS, ONNX_FILES,
                                            PARTS_JSON, URDF_FILE, UR_YAML, WORKSPACE_JSON, load_points)
from pipeline.lib.project.cli import script, stage_main
from pipeline.lib.project.columns import JOINTS_DEG, THEORY
from pipeline.lib.project.config import for_stage, json_text, logger, read_json
from pipeline.lib.project.writing import write_together
from pipeline.lib.robot.geometry import Calibration, theory_geometry, with_parts
from pipeline.lib.robot.identify import identify
from pipeline.lib.robot.kinematics import DTYPE, RIGID_KEYS, TOOL_ROT, fk, fk_frames, fk_numpy, fk_pose
from pipeline.lib.robot.robots import TABLES, load_robot
from pipeline.lib.robot.tcp import AtTcp, in_flange, probe_offsets
from pipeline.lib.robot.urdf import (UR_YAML_NAMES, base_transform, flange_residual, joint_origins, to_urdf,
                                     ur_kinematics, ur_yaml_text)
from pipeline.lib.runtime.compensation import nominal_flange
from pipeline.lib.runtime.realtime import DAMPING, Realtime, two_steps
from pipeline.lib.runtime.solvers import pose_weight

log = logger(__name__)
PARAMS = ("robot", "calibrate", "compensate")


def urdf_poses(urdf_text: str, q_rad: np.ndarray, frame_name: str = "tool0") -> tuple[np.ndarray, np.ndarray]:
    """A frame's positions (n, 3) mm and rotations (n, 3, 3) by Pinocchio from URDF text at joint angles q (n, 6) rad."""
    m = pin.buildModelFromXML(urdf_text)
    d, frame = m.createData(), m.getFrameId(frame_name)
    p, R = [], []
    for q in q_rad:
        pin.framesForwardKinematics(m, d, q)
        p.append(d.oMf[frame].translation * 1000.0)
        R.append(d.oMf[frame].rotation.copy())
    return np.array(p), np.array(R)


def urdf_positions(urdf_text: str, q_rad: np.ndarray) -> np.ndarray:
    """tool0 positions (n, 3) mm by Pinocchio from URDF text at joint angles q (n, 6) rad."""
    return urdf_poses(urdf_text, q_rad)[0]


def ur_yaml_poses(kinematics: dict, q_rad: np.ndarray) -> np.ndarray:
    """Joint 6's frame (n, 4, 4), mm, by Pinocchio from the UR kinematics YAML: joint i's origin is
    entry i (x y z m, roll pitch yaw rad), revolute about its z, as the UR description builds it."""
    m, parent = pin.Model(), 0
    for name in UR_YAML_NAMES:                                               # by name, as a YAML reader would
        e = kinematics["kinematics"][name]
        placement = pin.SE3(pin.rpy.rpyToMatrix(e["roll"], e["pitch"], e["yaw"]), np.array([e["x"], e["y"], e["z"]]))
        parent = m.addJoint(parent, pin.JointModelRZ(), placement, name)
    d, out = m.createData(), []
    for q in q_rad:
        pin.forwardKinematics(m, d, q)
        T = d.oMi[parent].homogeneous.copy()
        T[:3, 3] *= 1000.0
        out.append(T)
    return np.array(out)


def rigid_equivalent(g: dict, q: torch.Tensor, cfg: dict) -> tuple[dict, dict]:
    """The rigid chain (no compliance, no error maps) closest to geometry g's positions at poses q: g
    itself when it is rigid, else identified (calibrate's groups but compliance) on g's own positions.
    Returns (geometry, {"mean_mm", "max_mm"} of its distance to g's positions, "left_out": what g has
    that the chain cannot hold})."""
    with torch.no_grad():
        p = fk(q, g).numpy()
    left_out = (["joint compliance under gravity"] if g["compliance"].any() else []) + \
        (["per-joint angle error maps"] if "amap_coef" in g and g["amap_coef"].any() else []) + \
        (["per-joint load error maps"] if "lmap_coef" in g and (g["lmap_step"] > 0).any() and g["lmap_coef"].any()
         else [])                                 # a load map with no torque to act on (no link masses) does nothing
    rigid = {k: v for k, v in g.items() if k in RIGID_KEYS} | {"compliance": torch.zeros(6, dtype=DTYPE)}
    if left_out:                                  # g's orientations too, where it has a probe rotation
        cfg = {**cfg, "params": [k for k in cfg["params"] if k != "compliance"], "loss": "linear"}
        with torch.no_grad():
            R = fk_pose(q, g)[1].numpy() if TOOL_ROT in g else None
        rigid = identify(q, p, rigid, cfg, R_meas=R)[0]
    with torch.no_grad():
        e = np.linalg.norm(fk(q, rigid).numpy() - p, axis=1)
    return rigid, {"mean_mm": float(e.mean()), "max_mm": float(e.max()), "left_out": left_out}


def rigid_fit_at_tools(g: dict, rigid: dict, q: torch.Tensor, tcp: dict | None) -> dict:
    """How far the rigid chain stays from g (the model's physics) where a tool is, not only at the marker
    (rigid_equivalent's mean_mm, max_mm): at each `robot.tcp` point (else 150 mm along the flange's x), each
    chain with the point in its own flange frame (tcp.in_flange), {"tcp": {name: {"mean_mm", "max_mm"}}};
    where g has the probe's rotation, the orientation of its frame (tool0) too, {"orientation_arcsec": {"mean", "max"}}."""
    out = {"tcp": {}}
    for name, c in (tcp or {"x150": {"xyz_mm": [150.0, 0.0, 0.0]}}).items():
        with torch.no_grad():
            at = [fk_pose(q, with_tool(chain, in_flange({name: c}, chain)[name]))[0].numpy() for chain in (g, rigid)]
        e = np.linalg.norm(at[0] - at[1], axis=1)
        out["tcp"][name] = {"mean_mm": float(e.mean()), "max_mm": float(e.max())}
    if TOOL_ROT in g:
        with torch.no_grad():
            R = [fk_pose(q, chain)[1].numpy() for chain in (g, rigid)]
        a = Rotation.from_matrix(np.einsum("nji,njk->nik", *R)).magnitude() * 206264.806
        out["orientation_arcsec"] = {"mean": float(a.mean()), "max": float(a.max())}
    return out


def run(params: dict, root: Path = HERE) -> dict:
    """Every file of the stage, made and checked in a temporary folder, then written together (writing.py):
    a run that fails leaves the files of the run before it, all of them, none replaced."""
    with tempfile.TemporaryDirectory(prefix="export.") as tmp:
        files, summary = made_and_checked(params, root, Path(tmp))
    write_together(files)
    log.info("wrote %s", ", ".join(str(f) for f in files))
    return summary


def chain_files(g: dict, robot, tcp: dict | None, q: torch.Tensor, root: Path) -> tuple[dict, dict]:
    """The rigid chain g's URDF and UR YAML {path under root: text}, with every `robot.tcp` point (tcp, in g's
    flange frame), each read back by Pinocchio at joint angles q (n, 6) rad: (files, export.json's `urdf` and
    `ur_yaml`)."""
    with torch.no_grad():
        p_rigid, flange6 = fk(q, g).numpy(), fk_frames(q, g)[-1].numpy()      # flange6 (n, 4, 4) before the base
    summary = {}
    text = to_urdf(g, robot, tcp=tcp)
    files = {root / URDF_FILE: text}
    p_urdf, R_urdf = urdf_poses(text, q.numpy())
    dev = np.linalg.norm(p_urdf - p_rigid, axis=1)
    summary["urdf"] = {"file": str(URDF_FILE), "checked_with": f"pinocchio {pin.__version__}",
                       "max_deviation_mm": float(dev.max())}
    if TOOL_ROT in g:                               # tool0 is the probe's frame: its orientation checked too
        with torch.no_grad():
            R_rigid = fk_pose(q, g)[1].numpy()
        summary["urdf"]["max_rotation_deviation_arcsec"] = size(
            Rotation.from_matrix(np.einsum("nji,njk->nik", R_urdf, R_rigid)).magnitude().max() * 206264.806)
    log.info("%s: Pinocchio's tool0 vs the exported chain's FK on %d poses: max %.2e mm", root / URDF_FILE, len(q),
             dev.max())
    if not ((robot.velocity_rad_s > 0).all() and (robot.effort_nm > 0).all()):     # a custom robot's, not given
        summary["urdf"]["speed_and_torque_limits"] = (
            "unknown (robot.dh.velocity_deg_s, effort_nm not given): written as 0, which a planner reads as a joint "
            "that cannot move")
        log.warning("%s: %s", root / URDF_FILE, summary["urdf"]["speed_and_torque_limits"])
    if tcp:                                         # each tcp_<name> link too, against the chain at that point
        summary["urdf"]["tcp"] = tcp_links(text, tcp, q, g)
        log.info("%s: Pinocchio's tcp links vs the exported chain's FK: %s", root / URDF_FILE, summary["urdf"]["tcp"])

    kin = ur_kinematics(g, tcp)                     # any robot's chain fits the layout; a UR's driver reads it
    files[root / UR_YAML] = ur_yaml_text(kin)      # a tcp name a YAML 1.2 reader takes for a number: quoted
    truth = base_transform(g) @ flange6 @ np.linalg.inv(joint_origins(g)[1])   # joint 6's frame
    poses = ur_yaml_poses(kin, q.numpy())
    dev = np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)
    summary["ur_yaml"] = {"file": str(UR_YAML), "checked_with": f"pinocchio {pin.__version__}",
                          "max_deviation_mm": float(dev.max()),
                          "not_held_after_joint_6": flange_residual(g)}
    if robot.name not in TABLES:
        summary["ur_yaml"]["robot"] = f"{robot.name}: no Universal Robots arm; its chain in the UR description's layout"
    log.info("%s: joint 6's frame from the YAML vs the exported chain: max %.2e mm; the flange "
             "transform after joint 6 it cannot hold: %s", root / UR_YAML, dev.max(),
             summary["ur_yaml"]["not_held_after_joint_6"])
    return files, summary


def made_and_checked(params: dict, root: Path, tmp: Path) -> tuple[dict, dict]:
    """The stage's files {path under root: text or bytes}, each read back and checked (the ONNX graphs from
    their copies in tmp), and export.json's summary."""
    p = for_stage(params, PARAMS)
    robot = load_robot(p["robot"])
    pts = load_points(root)
    q = torch.as_tensor(np.radians(pts[JOINTS_DEG].to_numpy()), dtype=DTYPE)
    calibrated = with_parts(Calibration.from_dict(read_json(root / CALIBRATED_GEOMETRY)).geometry, read_json(root / PARTS_JSON))
    g, fit = rigid_equivalent(calibrated, q, p["calibrate"])      # the model's physics branch, as a rigid chain
    fit.update(rigid_fit_at_tools(calibrated, g, q, p["robot"]["tcp"]))
    summary = {"n_poses": len(pts), "rigid_fit": fit}
    log.info("the calibrated model as a rigid chain: %.4f mm mean, %.4f mm max from it on %d poses; at its tools "
             "%s; its frame's (tool0's) orientation %s", fit["mean_mm"], fit["max_mm"], len(pts), fit["tcp"],
             fit.get("orientation_arcsec", "not measured"))
    files, checked = chain_files(g, robot, in_flange(p["robot"]["tcp"], g), q, root)
    summary.update(checked)

    network = Workspace.from_dict(read_json(root / WORKSPACE_JSON)).network
    model = served(load_model(root / MODEL_WEIGHTS), network)    # evaluate's verdict: what the cell gets
    summary["network_kept"] = network
    at = {f: tmp / f.name for f in ONNX_FILES}                    # the graphs, read back from here first
    export_all(model, {f.stem: at[f] for f in ONNX_FILES})
    test = (pts["split"] == "test").to_numpy()
    q32 = q[test].float().clone()
    onnx_p = OnnxModel(at[MODEL_ONNX])(q32.numpy())
    with torch.no_grad():
        same, f64 = model(q32.double())[0].numpy(), model(q[test])[0].numpy()
        R_same = fk_pose(q32.double(), model.physics.geometry())[1].numpy()
    R_onnx = OnnxModel(at[MODEL_ONNX]).pose(q32.numpy())[1]
    summary["onnx"] = {"file": str(MODEL_ONNX), "checked_with": "onnxruntime", "n_test_poses": int(test.sum()),
                       "max_deviation_mm": size(np.abs(onnx_p - same).max()),
                       "max_deviation_from_float64_angles_mm": size(np.abs(onnx_p - f64).max()),
                       "max_rotation_deviation_arcsec": size(Rotation.from_matrix(np.einsum(
                           "nji,njk->nik", R_onnx, R_same)).magnitude().max() * 206264.806)}
    log.info("%s: onnxruntime vs PyTorch on %d test poses: max %.2e mm on the same float32 angles, %.2e mm "
             "from the float64 angles", root / MODEL_ONNX, test.sum(), summary["onnx"]["max_deviation_mm"],
             summary["onnx"]["max_deviation_from_float64_angles_mm"])

    limits = np.radians(robot.limits_deg)
    for key, f, m in (("controller", CONTROLLER_ONNX, model), ("controller_physics", CONTROLLER_PHYSICS_ONNX,
                                                                      PhysicsOnly(model))):
        path = root / f
        dev = deviation(Realtime(m, limits), OnnxRealtime(at[f], limits), q[test].numpy(),
                        pts.loc[test, THEORY].to_numpy())
        dev.update(max_q_rad=size(dev["max_q_rad"]), max_residual_mm=size(dev["max_residual_mm"]))
        summary[key] = {"file": str(f), "checked_with": "onnxruntime", **dev}
        log.info("%s: onnxruntime's answers vs the PyTorch controller path's on %d test poses (alone and in a "
                 "batch): max %.1e rad, residual %.1e mm; flags differ in %d", path, test.sum(),
                 dev["max_q_rad"], dev["max_residual_mm"], dev["flags_differ"])
    tcps = {n: c["xyz_mm"] for n, c in (in_flange(p["robot"]["tcp"], model.physics.geometry())
                                        or {"x150": {"xyz_mm": [150.0, 0.0, 0.0]}}).items()}
    for key, f, m in (("controller_tcp", CONTROLLER_TCP_ONNX, model),
                      ("controller_physics_tcp", CONTROLLER_PHYSICS_TCP_ONNX, PhysicsOnly(model))):
        path = root / f
        summary[key] = {"file": str(f), "checked_with": "onnxruntime"}
        for name, xyz in tcps.items():
            o = probe_offsets({name: {"xyz_mm": xyz}}, m.physics.geometry())[name]
            target = fk_numpy(pts.loc[test, JOINTS_DEG].to_numpy(), robot, theory_geometry(robot, xyz))
            dev = deviation(Realtime(AtTcp(m, o), limits), OnnxRealtime(at[f], limits, tcp_mm=xyz), q[test].numpy(),
                            target)
            summary[key][name] = {**dev, "max_q_rad": size(dev["max_q_rad"]),
                                  "max_residual_mm": size(dev["max_residual_mm"])}
            log.info("%s at TCP %s: onnxruntime vs PyTorch (AtTcp) on %d test poses: max %.1e rad, residual "
                     "%.1e mm; flags differ in %d", path, name, test.sum(), dev["max_q_rad"], dev["max_residual_mm"],
                     dev["flags_differ"])
    w = pose_weight(p["compensate"])
    nominal = theory_geometry(robot, read_json(root / FRAME_JSON)["tool_mm"])
    rot = nominal_flange(pts.loc[test, JOINTS_DEG].to_numpy(), nominal)
    summary["controller_pose"] = {"file": str(CONTROLLER_POSE_ONNX), "checked_with": "onnxruntime", "weight_mm_per_rad": w}
    for name, xyz in tcps.items():
        target = fk_numpy(pts.loc[test, JOINTS_DEG].to_numpy(), robot, theory_geometry(robot, xyz))
        got = OnnxRealtime(at[CONTROLLER_POSE_ONNX], limits, tcp_mm=xyz, weight=w).solve(q[test].numpy(), target, rot=rot)
        lo, hi = (torch.as_tensor(limits[:, i], dtype=DTYPE) for i in (0, 1))
        with torch.no_grad():
            want = [t.numpy() for t in two_steps(model.eval(), q[test], torch.as_tensor(target), lo, hi, DAMPING,
                                                 torch.as_tensor(xyz, dtype=DTYPE), torch.as_tensor(rot), w)]
        summary["controller_pose"][name] = {
            "n_poses": int(test.sum()), "max_q_rad": size(max(np.abs(a - b).max() for a, b in zip(got[:2], want[:2]))),
            "max_residual_mm": size(max(np.abs(a - b).max() for a, b in zip(got[2:], want[2:]))),
            "verified_share": float((got[3] < p["compensate"]["tol_mm"]).mean())}
        log.info("%s at TCP %s: onnxruntime vs PyTorch on %d test poses' nominal poses: max %.1e rad, |r| %.1e mm; "
                 "%.0f%% verified in one step", root / CONTROLLER_POSE_ONNX, name, test.sum(),
                 summary["controller_pose"][name]["max_q_rad"], summary["controller_pose"][name]["max_residual_mm"],
                 100 * summary["controller_pose"][name]["verified_share"])
    files.update({root / f: at[f].read_bytes() for f in ONNX_FILES})
    files[root / EXPORT_JSON] = json_text(summary)
    return files, summary


def tcp_links(urdf_text: str, tcp: dict, q: torch.Tensor, g: dict) -> dict:
    """{name: max position (mm) and rotation (arcsec) deviation} of each tcp_<name> link Pinocchio reads from the
    URDF against the chain g's FK at that point ({xyz_mm, rxyz_deg} in the flange frame) at joint angles q (n, 6)."""
    out = {}
    for name, c in tcp.items():
        p_urdf, R_urdf = urdf_poses(urdf_text, q.numpy(), f"tcp_{name}")
        with torch.no_grad():
            p, R = (t.numpy() for t in fk_pose(q, with_tool(g, c)))
        out[name] = {"max_deviation_mm": float(np.linalg.norm(p_urdf - p, axis=1).max()),
                     "max_rotation_deviation_arcsec": size(Rotation.from_matrix(np.einsum(
                         "nji,njk->nik", R_urdf, R)).magnitude().max() * 206264.806)}
    return out


def with_tool(g: dict, c: dict) -> dict:
    """Geometry g with its tool at the point c ({xyz_mm, rxyz_deg}, g's flange frame): FK gives that point's pose."""
    return {**g, "tool": torch.as_tensor(c["xyz_mm"], dtype=DTYPE),
            TOOL_ROT: torch.as_tensor(np.radians(c.get("rxyz_deg", [0.0, 0.0, 0.0])), dtype=DTYPE)}


def size(x) -> float:
    """A deviation onnxruntime measured, to 2 significant digits: its last bits follow the kernels
    onnxruntime picks for the CPU it finds, and export.json is a DVC output (docs/decisions.md)."""
    return float(f"{float(x):.2g}")


main = stage_main(__spec__.name, __doc__, run)         # main(argv=None, root=HERE)


if __name__ == "__main__":
    script(__spec__.name, main)

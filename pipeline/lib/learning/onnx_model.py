"""The trained model as ONNX (physics branch + network + fade, eq. 9): `q_rad` (batch, 6) float32 in,
`p_mm` (batch, 3) float64 and `probe_rot` (batch, 3, 3) float64 out, base frame: the marker's position and
the probe's orientation (the physics branch's: the network corrects positions), so the pose of any TCP
follows, p + R o (lib/robot/tcp.py; docs/data-format.md, "Exports for the robot cell"). And the
controller path (realtime.py: both chord steps, two evaluations of the model) as one graph, run by
`OnnxRealtime` as Realtime runs it in PyTorch:

    q0_rad (batch, 6), target_mm (batch, 3), q_min_rad (6,), q_max_rad (6,), damping (batch,)   float64
      -> q1_rad (batch, 6), q2_rad (batch, 6), r0_mm (batch,), r1_mm (batch,)                    float64

`damping` is each row's μ: the controller's (realtime.DAMPING, 1e-9), or, for the service's lm set,
each request's λ (`OnnxRealtime.lm_step`: q1 is lm's trial step and r1 its residual, one run an
iteration).

`models/controller_tcp.onnx` (and `controller_physics_tcp.onnx`) take one more input, `tcp_mm` (3,)
float64, the TCP in the flange frame (`robot.tcp`'s xyz_mm): the same two steps for that point's
position (`OnnxRealtime(path, ..., tcp_mm=...)`, what `python -m pipeline.commands.serve --tcp` runs).
`models/controller_pose.onnx` takes `tcp_mm` and POSE_INPUTS: a pose, six equations a step (the 6×6 solve
in closed form, solvers.solve_spd); |r| is then the weighted norm (`OnnxRealtime(..., tcp_mm, weight)`,
`solve(..., rot=...)`).

The joint limits are inputs, not constants: the graph is the model's alone, as model.onnx is, and a
change of the robot's limits cannot leave it answering with old ones. The 3×3 linear solve of each
step runs in closed form in the graph (solvers.solve3: ONNX has no solve), the error maps' table
look-ups as Gather; the answers equal PyTorch's to ~1e-12 rad (tests/test_compensate.py).

Exported with torch.onnx's dynamo exporter (torch.export, batch size left free); the physics branch
stays float64 inside the graph, as in PyTorch. Read back with onnxruntime (`OnnxModel`). Every graph is
optimised here (`optimise`), not by the exporter: its pattern rules run on the folded graph
(docs/decisions.md).

The file is the same bytes for the same weights (a DVC output, hashed in dvc.lock): the exporter's
debugging annotations (`metadata_props` on nodes, values, graph and model, and doc strings) are
dropped, since they carry the absolute path and line numbers of the exported source (each node's
`pkg.torch.onnx.stack_trace`), which differ between clones. They never reach the predictions.
"""
import logging
import shutil
import time
import warnings

import numpy as np
import torch
from torch import nn

from pipeline.lib.learning.model import Ensemble, PhysicsOnly
from pipeline.lib.project.config import logger
from pipeline.lib.project.writing import write_by
from pipeline.lib.robot.kinematics import DTYPE, fk_pose
from pipeline.lib.runtime.realtime import DAMPING, Result, answers, two_steps
from pipeline.lib.runtime.solvers import lm_keep

log = logger(__name__)

CONTROLLER_INPUTS = ("q0_rad", "target_mm", "q_min_rad", "q_max_rad", "damping")
TCP_INPUT = "tcp_mm"                # export_controller(..., at_tcp=True): the TCP (3,) mm, flange frame
POSE_INPUTS = ("target_rot", "weight")   # export_controller(..., pose=True): the flange's orientation (batch, 3, 3)
                                         # and its weight (1,) mm/rad (solvers.pose_weight)
CONTROLLER_OUTPUTS = ("q1_rad", "q2_rad", "r0_mm", "r1_mm")


class _Poses(nn.Module):
    """The model seen as q (float32 rad) -> predicted position (float64 mm) and the probe's orientation."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, q_rad):                              # (B, 6) float32 -> (B, 3), (B, 3, 3) float64
        q = q_rad.double()
        return self.model(q)[0], fk_pose(q, self.model.physics.geometry())[1]


class _Controller(nn.Module):
    """The controller path's two chord steps (realtime.two_steps) as a module, for the exporter, at a TCP given
    as an input (3,) mm in the flange frame: one graph for every tool (the marker's own graph is this one with
    the TCP fixed at the probe offset, `at_probe`)."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, q0_rad, target_mm, q_min_rad, q_max_rad, damping, tcp_mm):
        return two_steps(self.model, q0_rad, target_mm, q_min_rad, q_max_rad, damping, tcp_mm)


class _ControllerPose(_Controller):
    """The same for a pose: a TCP's position and the flange's orientation, six equations."""

    def forward(self, q0_rad, target_mm, q_min_rad, q_max_rad, damping, tcp_mm, target_rot, weight):
        return two_steps(self.model, q0_rad, target_mm, q_min_rad, q_max_rad, damping, tcp_mm, target_rot, weight)


def export_all(model, paths: dict) -> dict:
    """Every graph of the export stage from four traces, in its order: paths {file stem: Path} for model,
    controller_tcp and controller, controller_physics_tcp and controller_physics (the marker graphs from
    their TCP graphs' traces), controller_pose. The seconds of each trace, {what: s}. A model that is its
    physics branch already (model.served without the network) has physics graphs that are its own, to the
    byte: they are copied, not traced again."""
    traces = {
        "model": lambda: export_onnx(model, paths["model"]),
        "controller_tcp and controller (one trace)":
            lambda: export_controller(model, paths["controller_tcp"], at_tcp=True, probe_path=paths["controller"]),
        "controller_physics_tcp and controller_physics (one trace)":
            lambda: export_controller(PhysicsOnly(model), paths["controller_physics_tcp"], at_tcp=True,
                                      probe_path=paths["controller_physics"]),
        "controller_pose": lambda: export_controller(model, paths["controller_pose"], pose=True),
    }
    if isinstance(model, PhysicsOnly):
        del traces["controller_physics_tcp and controller_physics (one trace)"]
        traces["controller_physics_tcp and controller_physics (copies: the model is its physics)"] = lambda: [
            shutil.copyfile(paths[own], paths[copy])
            for own, copy in (("controller_tcp", "controller_physics_tcp"), ("controller", "controller_physics"))]
    seconds = {}
    for what, export in traces.items():
        t = time.perf_counter()
        export()
        seconds[what] = time.perf_counter() - t
        log.info("exported %s in %.1f s", what, seconds[what])
    return seconds


def export_onnx(model, path) -> None:
    """Write `model` (BoTER or Ensemble, eval mode) to `path` as ONNX."""
    save(_export(_Poses(_exportable(model)), (torch.zeros(4, 6),), ["q_rad"], ["p_mm", "probe_rot"],
                 ({0: "batch"},)), path)


def export_controller(model, path, at_tcp: bool = False, pose: bool = False, probe_path=None) -> None:
    """Write the controller path of `model` (BoTER or Ensemble, eval mode) to `path` as one ONNX graph:
    both chord steps, exactly what realtime.Realtime computes with the same damping; at_tcp: with the input
    `tcp_mm` (3,), the TCP in the flange frame, whose position the targets are (Realtime on tcp.AtTcp), and
    with probe_path, the marker's graph too (`at_probe`), from the same trace; pose: that, and the flange's
    orientation as a target too (POSE_INPUTS; realtime.two_steps' rot, w)."""
    m = _exportable(model)
    for p in m.parameters():
        p.requires_grad_(False)
    args = (torch.zeros(4, 6, dtype=DTYPE), torch.zeros(4, 3, dtype=DTYPE), torch.full((6,), -np.pi, dtype=DTYPE),
            torch.full((6,), np.pi, dtype=DTYPE), torch.full((4,), DAMPING, dtype=DTYPE), torch.zeros(3, dtype=DTYPE))
    dynamic = ({0: "batch"}, {0: "batch"}, None, None, {0: "batch"}, None)
    names = list(CONTROLLER_INPUTS) + [TCP_INPUT]
    if pose:
        save(_export(_ControllerPose(m), args + (torch.eye(3, dtype=DTYPE).expand(4, 3, 3).clone(),
                                                 torch.ones(1, dtype=DTYPE)),
                     names + list(POSE_INPUTS), list(CONTROLLER_OUTPUTS), dynamic + ({0: "batch"}, None)), path)
        return
    graph = _export(_Controller(m), args, names, list(CONTROLLER_OUTPUTS), dynamic)
    if at_tcp:
        save(graph, path)
    marker_path = probe_path if at_tcp else path            # where the marker's graph goes, if anywhere
    if marker_path is not None:
        save(at_probe(graph, m.physics.geometry()["tool"]), marker_path)


def at_probe(graph, tool_mm: torch.Tensor):
    """The TCP controller graph (an onnx_ir Model, changed in place and returned) as the marker's: its input
    tcp_mm fixed at the probe offset tool_mm (3,) (two_steps without a TCP: the physics branch's own tool),
    then `optimise`d. onnxruntime answers as the graph traced without the input, to the bit (tests/test_export.py)."""
    import onnx_ir as ir
    tcp = next(v for v in graph.graph.inputs if v.name == TCP_INPUT)
    graph.graph.inputs.remove(tcp)
    tcp.const_value = ir.tensor(tool_mm.detach().numpy().astype(np.float64))
    graph.graph.register_initializer(tcp)
    optimise(graph)
    return graph


def _exportable(model):
    return (model.for_export() if isinstance(model, Ensemble) else model).eval()


def _export(module, args, inputs, outputs, dynamic):
    """torch.onnx (dynamo) export of module at args, the dims named in dynamic free, optimised by `optimise`:
    an onnx_ir Model."""
    for name in ("onnxscript", "onnx_ir"):                # their graph passes log every rewrite at INFO
        logging.getLogger(name).setLevel(logging.WARNING)
    # "torchvision is not installed": four warnings a graph about ops no model here uses
    logging.getLogger("torch.onnx._internal.exporter._registration").setLevel(logging.ERROR)
    dims = {}
    shapes = tuple(None if d is None else {i: dims.setdefault(n, torch.export.Dim(n)) for i, n in d.items()}
                   for d in dynamic)
    with warnings.catch_warnings():                        # two inputs sharing the batch axis: said, harmless
        warnings.filterwarnings("ignore", "# The axis name: .* will not be used")
        program = torch.onnx.export(module.eval(), args, None, input_names=inputs, output_names=outputs,
                                    dynamic_shapes=shapes, dynamo=True, optimize=False, verbose=False)
    optimise(program.model)
    return program.model


def save(graph, path) -> None:
    """An onnx_ir Model to path without the exporter's annotations (strip_annotations), as one self-contained
    file, whole or not at all."""
    import onnx
    import onnx_ir as ir
    proto = ir.serde.serialize_model(graph)
    strip_annotations(proto)
    write_by(path, lambda p: onnx.save_model(proto, str(p), save_as_external_data=False))


def optimise(model) -> None:
    """In place on an onnx_ir Model: `fold`, onnxscript's default pattern rules on the folded graph, `fold`
    again. The exporter's own optimiser (optimize_ir) runs the same rules before the dead nodes are
    removed, at several times the cost (the controller graph: 15.8 s against 4.2) for the same nodes and
    onnxruntime's answers to the bit (docs/decisions.md)."""
    from onnxscript import rewriter
    fold(model)
    rewriter.rewrite(model)                                # its default rules, in place on an ir.Model
    fold(model)


def fold(model) -> None:
    """onnxscript's graph optimisation (its optimize_ir) without the pattern rewriter, in place on an
    onnx_ir Model: functions inlined, constants folded, unused nodes removed, constants lifted to
    initializers and deduplicated, common subexpressions merged."""
    import onnxscript.optimizer as optimizer
    from onnx_ir.passes import common
    optimizer.inline(model)
    optimizer.fold_constants(model, onnx_shape_inference=True)
    for step in (common.RemoveUnusedNodesPass(), common.LiftConstantsToInitializersPass(lift_all_constants=True,
                                                                                        size_limit=0),
                 common.DeduplicateInitializersPass(), common.CommonSubexpressionEliminationPass(),
                 common.RemoveUnusedNodesPass(), common.NameFixPass()):
        step(model)


def strip_annotations(proto) -> None:
    """Drop every `metadata_props` and `doc_string` of an ONNX ModelProto, in place (functions and
    subgraphs included): the exporter's annotations, which name source paths and lines."""
    def values(g):
        return [*g.input, *g.output, *g.value_info, *g.initializer,
                *(t for s in g.sparse_initializer for t in (s.values, s.indices))]

    def graph(g):
        g.ClearField("doc_string")
        del g.metadata_props[:]
        for v in values(g):
            v.ClearField("doc_string")
            del v.metadata_props[:]
        nodes(g.node)

    def nodes(ns):
        for n in ns:
            n.ClearField("doc_string")
            del n.metadata_props[:]
            for a in n.attribute:
                a.ClearField("doc_string")
                if a.HasField("g"):
                    graph(a.g)
                for sub in a.graphs:
                    graph(sub)

    proto.ClearField("doc_string")
    del proto.metadata_props[:]
    graph(proto.graph)
    for f in proto.functions:
        f.ClearField("doc_string")
        del f.metadata_props[:]
        for v in f.value_info:
            del v.metadata_props[:]
        nodes(f.node)


class OnnxModel:
    """`OnnxModel(path)(q_rad (n, 6)) -> p_mm (n, 3)` with onnxruntime on one CPU thread."""

    def __init__(self, path):
        self.session = session(path)

    def __call__(self, q_rad) -> np.ndarray:
        return self.session.run(["p_mm"], {"q_rad": np.asarray(q_rad, np.float32).reshape(-1, 6)})[0]

    def pose(self, q_rad) -> tuple[np.ndarray, np.ndarray]:
        """(p_mm (n, 3), probe_rot (n, 3, 3))."""
        return tuple(self.session.run(["p_mm", "probe_rot"], {"q_rad": np.asarray(q_rad, np.float32).reshape(-1, 6)}))


def session(path, fixed: dict | None = None):
    """An onnxruntime session on one CPU thread (what every runner here uses); fixed: free dimensions held
    at a size ({"batch": 1}: shapes known when the session is made, its memory planned once, ~7% faster)."""
    import onnxruntime as ort
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1
    for name, size in (fixed or {}).items():
        opts.add_free_dimension_override_by_name(name, size)
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


class OnnxRealtime:
    """The controller path on onnxruntime, one thread: `OnnxRealtime(path, limits_rad)(q0_rad, target_mm)
    -> realtime.Result`, as `Realtime(model, limits_rad)` answers (the same two steps, exported by
    `export_controller`); `batch` for B poses in one run. No model needed: the file is the whole solve.
    A single pose runs on a session with the batch size held at 1, a batch on one with it free."""

    def __init__(self, path, limits_rad: np.ndarray | None = None, tol_mm: float = 1e-3, workspace=None,
                 damping: float = DAMPING, tcp_mm=None, weight: float | None = None):
        self.session, self.tol, self.workspace, self.damping = session(path), tol_mm, workspace, float(damping)
        names = tuple(i.name for i in self.session.get_inputs())
        want = CONTROLLER_INPUTS + (() if tcp_mm is None else (TCP_INPUT,)) + (() if weight is None else POSE_INPUTS)
        if names != want:
            raise ValueError(f"{path}: a graph with inputs {', '.join(names)}, not the controller path's "
                             f"{', '.join(want)} (exported by an older version, or for another tool?)")
        self.single = session(path, {self.session.get_inputs()[0].shape[0]: 1})
        self.limits = np.array([[-np.inf, np.inf]] * 6) if limits_rad is None else np.asarray(limits_rad, float)
        self.fixed = {"q_min_rad": np.ascontiguousarray(self.limits[:, 0]),
                      "q_max_rad": np.ascontiguousarray(self.limits[:, 1])}
        if tcp_mm is not None:                             # the graph's inputs held for every call
            self.fixed[TCP_INPUT] = np.array(tcp_mm, np.float64).reshape(3)
        if weight is not None:
            self.fixed["weight"] = np.array([weight], np.float64)

    def solve(self, q0_rad, target_mm, damping=None, rot=None) -> list[np.ndarray]:
        """The graph's outputs for q0 (B, 6) rad, target (B, 3) mm, damping (B,) (None: the controller's) and,
        on a pose graph, the flange's orientations rot (B, 3, 3): q1, q2 (B, 6), |r0|, |r1| (B,)."""
        if (rot is None) != ("weight" not in self.fixed):
            raise ValueError("a pose graph (controller_pose.onnx, weight given) solves a target's orientation too: "
                             "give rot (B, 3, 3)" if rot is None else
                             "rot given to a position graph: the orientation is controller_pose.onnx's (and weight)")
        q0 = np.asarray(q0_rad, np.float64).reshape(-1, 6)
        mu = np.full(len(q0), self.damping) if damping is None else np.asarray(damping, np.float64).reshape(-1)
        pose = {} if rot is None else {"target_rot": np.ascontiguousarray(np.asarray(rot, np.float64).reshape(-1, 3, 3))}
        return (self.single if len(q0) == 1 else self.session).run(
            None, {"q0_rad": q0, "target_mm": np.asarray(target_mm, np.float64).reshape(-1, 3), **self.fixed,
                   "damping": mu, **pose})

    def __call__(self, q0_rad, target_mm, rot=None) -> Result:
        return self.batch(q0_rad, target_mm, rot)[0]

    def batch(self, q0_rad, target_mm, rot=None) -> list[Result]:
        return answers(*self.solve(q0_rad, target_mm, rot=rot), self.tol, self.workspace, self.limits)

    def lm_step(self, q, target, err, lam):
        """solvers.lm_step on the graph, numpy: q (A, 6) rad, target (A, 3) mm, |r| err (A,) mm, λ lam (A,)
        -> the new q, err, lam. One run: its first chord step, damped by λ, is lm's trial (q1, |r1|); the
        second is not used. As lm with compensate.jacobian_of physics (the same step and residual)."""
        q1, _, _, r1 = self.solve(q, target, lam)
        return lm_keep(r1 < err, q1, r1, q, err, lam)


def deviation(a, b, q0_rad: np.ndarray, target_mm: np.ndarray) -> dict:
    """How far two controller paths (Realtime, OnnxRealtime) answer apart on the pairs (n, 6), (n, 3),
    each pose alone and all in one batch: the largest |Δq| (rad) and |Δ residual_mm|, and how many
    answers differ in verified, converged or in_workspace."""
    ra = [a(x, y) for x, y in zip(q0_rad, target_mm)] + a.batch(q0_rad, target_mm)
    rb = [b(x, y) for x, y in zip(q0_rad, target_mm)] + b.batch(q0_rad, target_mm)
    dq = max(float(np.abs(x.q - y.q).max()) for x, y in zip(ra, rb))
    dr = max(abs(x.residual_mm - y.residual_mm) if np.isfinite(x.residual_mm) or np.isfinite(y.residual_mm)
             else 0.0 for x, y in zip(ra, rb))
    flags = sum((x.verified, x.converged, x.in_workspace) != (y.verified, y.converged, y.in_workspace)
                for x, y in zip(ra, rb))
    return {"n_answers": len(ra), "max_q_rad": dq, "max_residual_mm": dr, "flags_differ": int(flags)}

"""The trained model as ONNX (physics branch + network + fade, eq. 9): `q_rad` (batch, 6) float32 in,
`p_mm` (batch, 3) float64 out, base frame (docs/data-format.md, "Exports for the robot cell").

Exported with torch.onnx's dynamo exporter (torch.export, batch size left free); the physics branch
stays float64 inside the graph, as in PyTorch. Read back with onnxruntime (`OnnxModel`).

The file is the same bytes for the same weights (a DVC output, hashed in dvc.lock): the exporter's
debugging annotations (`metadata_props` on nodes, values, graph and model, and doc strings) are
dropped, since they carry the absolute path and line numbers of the exported source (each node's
`pkg.torch.onnx.stack_trace`), which differ between clones. They never reach the predictions.
"""
import logging

import numpy as np
import torch
from torch import nn

from .model import Ensemble


class _Positions(nn.Module):
    """The model seen as q (float32 rad) -> predicted position (float64 mm)."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, q_rad):                              # (B, 6) float32 -> (B, 3) float64
        return self.model(q_rad.double())[0]


def export_onnx(model, path) -> None:
    """Write `model` (BoTER or Ensemble, eval mode) to `path` as ONNX."""
    for name in ("onnxscript", "onnx_ir"):                # their graph passes log every rewrite at INFO
        logging.getLogger(name).setLevel(logging.WARNING)
    if isinstance(model, Ensemble):
        model = model.for_export()
    batch = torch.export.Dim("batch")
    program = torch.onnx.export(_Positions(model).eval(), (torch.zeros(4, 6),), None, input_names=["q_rad"],
                                output_names=["p_mm"], dynamic_shapes=({0: batch},), dynamo=True,
                                verbose=False)
    import onnx
    proto = program.model_proto
    strip_annotations(proto)
    onnx.save_model(proto, str(path), save_as_external_data=False)   # one self-contained file


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
        import onnxruntime as ort
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = opts.inter_op_num_threads = 1
        self.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])

    def __call__(self, q_rad) -> np.ndarray:
        return self.session.run(["p_mm"], {"q_rad": np.asarray(q_rad, np.float32).reshape(-1, 6)})[0]

"""The trained model as ONNX (physics branch + network + fade, eq. 9): `q_rad` (batch, 6) float32 in,
`p_mm` (batch, 3) float64 out, base frame (DATA_FORMAT.md, "Exports for the robot cell").

Exported with torch.onnx's dynamo exporter (torch.export, batch size left free); the physics branch
stays float64 inside the graph, as in PyTorch. Read back with onnxruntime (`OnnxModel`).
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
    torch.onnx.export(_Positions(model).eval(), (torch.zeros(4, 6),), str(path), input_names=["q_rad"],
                      output_names=["p_mm"], dynamic_shapes=({0: batch},), dynamo=True, verbose=False,
                      external_data=False)                 # one self-contained file


class OnnxModel:
    """`OnnxModel(path)(q_rad (n, 6)) -> p_mm (n, 3)` with onnxruntime on one CPU thread."""

    def __init__(self, path):
        import onnxruntime as ort
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = opts.inter_op_num_threads = 1
        self.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])

    def __call__(self, q_rad) -> np.ndarray:
        return self.session.run(["p_mm"], {"q_rad": np.asarray(q_rad, np.float32).reshape(-1, 6)})[0]

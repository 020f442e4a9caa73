"""BoTER (sec. 2.1): physics branch + joint-token Transformer, fused as p = p_theory + α·Δp.

    q (B, 6) rad ──► DHChain ───────────────────────────────► p_theory (B, 3)
          └────► JointEmbedding (B, 6, d) ► Encoder(mask) ► Head ► Δp (B, 3)
    p_pred = p_theory + w(q)·α·Δp                                 (eq. 9)

w(q) (workspace.Fade, eval mode only) is 1 near the training poses and fades to 0 at
`fade_to` workspace radii from them: outside the joint space it learned from, the
model falls back on the physics it sits on instead of extrapolating (w = 1 is the paper).

The physics branch runs in float64 (positions ~1 m, wanted to 1e-3 mm); the
network in float32 (it only learns the ~1 mm error, and float32 trains 1.6x
faster on CPU); the fusion is float64.

Also the paper's DNN baseline (an MLP from joint angles to the position error).
"""
import copy
import itertools
import warnings

import numpy as np
import pandas as pd
import torch
from torch import nn

from pipeline.lib.learning.workspace import Fade
from pipeline.lib.project.columns import JOINTS_DEG, MEAS
from pipeline.lib.project.config import HEADS         # declared with the settings' rules
from pipeline.lib.robot.kinematics import DTYPE, DHChain

# eq. 4, row i = query joint i, True = may not attend (docs/method.md)
SPI_MASK = [[0, 0, 0, 0, 0, 0],
            [0, 0, 0, 0, 0, 0],
            [0, 0, 0, 0, 0, 0],
            [1, 1, 0, 0, 0, 0],
            [1, 1, 1, 0, 0, 0],
            [1, 1, 1, 0, 0, 0]]
# eq. 43 as printed, the Body-Transformer mask: each joint sees itself and its
# chain neighbours (docs/method.md words it "within 2 hops"; the printed matrix stands)
BODY_MASK = [[0, 0, 1, 1, 1, 1],
             [0, 0, 0, 1, 1, 1],
             [1, 0, 0, 0, 1, 1],
             [1, 1, 0, 0, 0, 1],
             [1, 1, 1, 0, 0, 0],
             [1, 1, 1, 1, 0, 0]]
MASKS = {"spi": SPI_MASK, "body": BODY_MASK, "none": None}


def attention_mask(kind: str) -> torch.Tensor | None:
    """The 6x6 bool attention mask (True = masked) of `model.mask`, or None."""
    if kind not in MASKS:
        raise ValueError(f"params.yaml model.mask: unknown mask {kind!r}; use one of {sorted(MASKS)}")
    m = MASKS[kind]
    return None if m is None else torch.tensor(m, dtype=torch.bool)


def check_config(cfg: dict) -> None:
    """Stop before training on a combination that cannot work, with a clear message: the names the model's
    registries hold (mask, head) and the rule between two keys; each value's own range is config.RULES'."""
    attention_mask(cfg["mask"])
    if cfg["head"] not in HEADS:
        raise ValueError(f"params.yaml model.head: unknown head {cfg['head']!r}; use one of {HEADS}")
    if cfg["d_model"] % cfg["n_head"]:
        d = cfg["d_model"]
        raise ValueError(f"params.yaml model: n_head={cfg['n_head']} does not divide d_model={d} "
                         f"(multi-head attention splits d_model into n_head equal parts); "
                         f"n_head could be {[h for h in range(1, d + 1) if d % h == 0][:12]}")


class JointEmbedding(nn.Module):
    """Eq. 2: an independent Linear(1, d_model) + ReLU per joint, all six applied at once."""

    def __init__(self, d_model: int):
        super().__init__()
        # six Linear(1, d) layers stored side by side: weight[i] is joint i's layer
        self.weight = nn.Parameter(torch.empty(6, d_model))
        self.bias = nn.Parameter(torch.empty(6, d_model))
        bound = 1.0  # nn.Linear's default init for fan_in = 1: U(-1/sqrt(1), 1/sqrt(1))
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, q):                                  # (B, 6) -> (B, 6, d)
        return torch.relu(q.unsqueeze(-1) * self.weight + self.bias)


class ResidualHead(nn.Module):
    """Eqs. 7-8: a = ReLU(L1 x); b = L2 a; r = Ls x; z = ReLU(b + r); Δp = Lo z.

    With shortcut=False (the "No ResNet" ablation) the same layers without Ls:
    z = ReLU(L2 a).
    """

    def __init__(self, d_in: int, d_hidden: int, shortcut: bool = True):
        super().__init__()
        self.l1, self.l2 = nn.Linear(d_in, d_hidden), nn.Linear(d_hidden, d_hidden)
        self.ls = nn.Linear(d_in, d_hidden) if shortcut else None
        self.out = nn.Linear(d_hidden, 3)

    def forward(self, x):                                  # (B, d_in) -> (B, 3)
        b = self.l2(torch.relu(self.l1(x)))
        z = torch.relu(b + self.ls(x)) if self.ls is not None else torch.relu(b)
        return self.out(z)


class BoTER(nn.Module):
    def __init__(self, geometry: dict, *, d_model: int, n_layer: int, n_head: int, d_hidden: int,
                 mask: str, head: str, encoder: bool, alpha0: float, dropout: float,
                 fade_to: float | None):
        """The `model:` section's settings (params.yaml owns the values)."""
        super().__init__()
        self.physics = DHChain(geometry)
        self.embed = JointEmbedding(d_model)
        self.register_buffer("mask", attention_mask(mask), persistent=False)
        self.encoder = nn.TransformerEncoder(
            nn.TransformerEncoderLayer(d_model, n_head, 4 * d_model, dropout, batch_first=True),
            n_layer, enable_nested_tensor=False) if encoder else None
        self.head = ResidualHead(6 * d_model, d_hidden, shortcut=(head == "resnet"))
        self.alpha = nn.Parameter(torch.tensor(float(alpha0)))   # eq. 9, trainable
        self.fade = Fade(fade_to)                          # fitted to the training poses by training

    def correction(self, q):                               # (B, 6) rad -> α·Δp (B, 3), float64
        x = self.embed(q.float())                          # (B, 6, d)
        if self.encoder is not None and torch.compiler.is_exporting():
            x = encoder_for_export(self.encoder, x, self.mask)
        elif self.encoder is not None:
            x = self.encoder(x, mask=self.mask, is_causal=False)   # (B, 6, d); skips a causal-mask probe
        return (self.alpha * self.head(x.flatten(1))).to(DTYPE)   # (B, 6d) -> (B, 3)

    def delta(self, q):                                    # (B, 6) rad -> w·α·Δp (B, 3), float64
        dp = self.correction(q)
        return dp if self.training else dp * self.fade(q)

    def forward(self, q):
        """q (B, 6) rad -> (p_pred, p_theory), both (B, 3) mm in the base frame."""
        p_theory = self.physics(q)
        return p_theory + self.delta(q), p_theory

    @torch.no_grad()
    def attention_maps(self, q) -> torch.Tensor:
        """Attention weights per layer and head: (n_layer, B, n_head, 6, 6)."""
        x, maps = self.embed(q.float()), []
        for layer in self.encoder.layers:
            _, w = layer.self_attn(x, x, x, attn_mask=self.mask, need_weights=True,
                                   average_attn_weights=False)
            maps.append(w)
            x = layer(x, src_mask=self.mask)
        return torch.stack(maps)


def encoder_for_export(encoder: nn.TransformerEncoder, x, mask):
    """encoder(x, mask) for ONNX export, the same arithmetic in fewer graph nodes: the tokens kept as
    one (B·6, d) matrix between layers (a Gemm each linear, no reshapes around them), q, k, v split
    once. A post-norm ReLU nn.TransformerEncoderLayer in eval mode (what BoTER builds); the answers
    equal the module's to float32 rounding (tests/test_model.py). (B, 6, d) -> (B, 6, d)."""
    B, n, d = x.shape
    masked = torch.zeros(n, n).masked_fill(mask, float("-inf")) if mask is not None else 0.0   # (6, 6)
    x = x.reshape(B * n, d)
    for layer in encoder.layers:
        a = layer.self_attn
        h = a.num_heads
        qkv = nn.functional.linear(x, a.in_proj_weight, a.in_proj_bias)            # (B·6, 3d)
        q, k, v = qkv.reshape(B, n, 3, h, d // h).permute(2, 0, 3, 1, 4).unbind(0)   # 3 × (B, h, 6, d/h)
        w = torch.softmax((q * (d // h) ** -0.5) @ k.transpose(-1, -2) + masked, -1)   # (B, h, 6, 6)
        y = (w @ v).transpose(1, 2).reshape(B * n, d)                              # (B·6, d)
        x = layer.norm1(x + a.out_proj(y))
        x = layer.norm2(x + layer.linear2(torch.relu(layer.linear1(x))))
    return x.reshape(B, n, d)


class Ensemble(nn.Module):
    """K BoTERs trained apart (seeds + k), evaluated as one batched call (inference only):

        p_pred = p_theory + w(q) · mean_k α_k Δp_k(q)

    The members' network weights are stacked (torch.func.stack_module_state: every tensor gains
    a leading K axis) and one weightless skeleton runs them all under torch.func.vmap. Physics and
    fade are shared: every member sits on the same physics branch and training poses.
    """

    def __init__(self, members: list[BoTER]):
        super().__init__()
        self.physics, self.fade = members[0].physics, members[0].fade
        self.n_members = len(members)
        params, buffers = torch.func.stack_module_state([Correction(m) for m in members])
        stacked = {k: v for k, v in {**params, **buffers}.items() if not k.startswith(("m.physics.", "m.fade."))}
        self.names = list(stacked)
        for k, v in stacked.items():                        # (K, ...) per tensor
            self.register_buffer(_key(k), v.detach())
        self.skeleton = [Correction(copy.deepcopy(members[0])).to("meta").eval()]   # a list: no submodule
        self.unstacked = None                              # for_export(): the members as plain modules

    def for_export(self) -> "Ensemble":
        """A copy that runs its members one by one (torch.export traces no vmap over a functional
        skeleton); the same numbers."""
        out = copy.deepcopy(self)
        members = []
        for k in range(self.n_members):
            m = copy.deepcopy(self.skeleton[0]).to_empty(device="cpu")
            tensors = dict(m.named_parameters()) | dict(m.named_buffers())    # incl. the non-persistent mask
            with torch.no_grad():
                for n in self.names:
                    tensors[n].copy_(getattr(self, _key(n))[k])
            members.append(m.eval())
        out.unstacked = nn.ModuleList(members)
        return out

    def correction(self, q):                               # (B, 6) rad -> mean_k α_k Δp_k (B, 3)
        if self.unstacked is not None:
            return torch.stack([m(q) for m in self.unstacked]).mean(0)
        stacked = {k: getattr(self, _key(k)) for k in self.names}
        one = lambda w, x: torch.func.functional_call(self.skeleton[0], w, (x,))
        fastpath = torch.backends.mha.get_fastpath_enabled()
        torch.backends.mha.set_fastpath_enabled(False)     # the fused encoder kernel has no vmap rule
        try:
            with warnings.catch_warnings():                # attention runs member by member inside
                warnings.filterwarnings("ignore", "There is a performance drop")
                return torch.func.vmap(one, in_dims=(0, None))(stacked, q).mean(0)   # (K, B, 3) -> (B, 3)
        finally:
            torch.backends.mha.set_fastpath_enabled(fastpath)

    def delta(self, q):
        return self.correction(q) * self.fade(q)

    def forward(self, q):
        p_theory = self.physics(q)
        return p_theory + self.delta(q), p_theory


class Correction(nn.Module):
    """A BoTER seen through its network correction α·Δp alone (what Ensemble stacks)."""

    def __init__(self, m: BoTER):
        super().__init__()
        self.m = m

    def forward(self, q):
        return self.m.correction(q)


def _key(name: str) -> str:
    return "stacked_" + name.replace(".", "__")


class PhysicsOnly(nn.Module):
    """A model's physics branch alone, seen as a model: p_pred = p_theory, Δp = 0. What a BoTER (or an
    Ensemble) answers wherever its correction has faded (w = 0): for a controller whose cycle cannot hold
    the network's evaluations (onnx_model.export_controller writes its controller path too)."""

    def __init__(self, model):
        super().__init__()
        self.physics = model.physics

    def delta(self, q):                                    # (B, 6) -> (B, 3) zeros
        return torch.zeros_like(q[:, :3])

    def forward(self, q):
        p = self.physics(q)
        return p, p


def served(model, network: bool):
    """What the robot cell gets: the whole model, or its physics branch alone when its network did not
    lower the validation error (evaluate's verdict, Workspace.network)."""
    return model if network else PhysicsOnly(model)


class DNN(nn.Module):
    """The paper's DNN baseline: an MLP from joint angles (rad) to the position error."""

    def __init__(self, geometry: dict, widths=(128, 128, 128)):
        super().__init__()
        self.physics = DHChain(geometry)
        layers, d = [], 6
        for w in widths:
            layers += [nn.Linear(d, w), nn.ReLU()]
            d = w
        self.mlp = nn.Sequential(*layers, nn.Linear(d, 3))

    def forward(self, q):
        p_theory = self.physics(q)
        return p_theory + self.mlp(q.float()).to(DTYPE), p_theory


def n_params(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def model_device(model) -> torch.device:
    """Where a model's tensors are (the CPU for a module without any)."""
    return next(itertools.chain(model.buffers(), model.parameters()), torch.empty(0)).device


def tensors(df: pd.DataFrame) -> tuple[torch.Tensor, torch.Tensor]:
    """Joint angles (n, 6) rad and measured positions (n, 3) mm as float64 tensors."""
    q = torch.tensor(np.radians(df[JOINTS_DEG].to_numpy()), dtype=DTYPE)
    return q, torch.tensor(df[MEAS].to_numpy(), dtype=DTYPE)


@torch.no_grad()
def predict(model, df: pd.DataFrame, batch: int = 4096) -> np.ndarray:
    """Model predictions (n, 3) mm, base frame (on the CPU, wherever the model is)."""
    q, _ = tensors(df)
    q = q.to(model_device(model))
    return torch.cat([model(qb)[0] for qb in q.split(batch)]).cpu().numpy()

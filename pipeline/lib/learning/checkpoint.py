"""The checkpoint: a trained model saved with its own config, and built back from it alone.

    make_model(cfg, geometry, kind)   BoTER (the `model:` section) or the DNN baseline, seeded
    save_model(model, path, cfg)      {"config", "members", "state_dict"} (torch.save)
    load_model(path)                  the model of a checkpoint, in eval mode; needs no params
"""
import torch

from pipeline.lib.learning.model import DNN, BoTER, Ensemble, check_config
from pipeline.lib.robot.errormaps import MAP_KEYS
from pipeline.lib.robot.kinematics import RIGID_KEYS


def make_model(cfg: dict, geometry: dict, kind: str = "boter"):
    """BoTER (the `model:` section) or the DNN baseline on `geometry`, weights from cfg["init_seed"]."""
    check_config(cfg)
    torch.manual_seed(cfg["init_seed"])
    if kind == "dnn":
        return DNN(geometry)
    return BoTER(geometry, d_model=cfg["d_model"], n_layer=cfg["n_layer"], n_head=cfg["n_head"],
                 d_hidden=cfg["d_hidden"], mask=cfg["mask"], head=cfg["head"], encoder=cfg["encoder"],
                 alpha0=cfg["alpha0"], dropout=cfg["dropout"], fade_to=cfg["fade_to"])


def save_model(model, path, cfg: dict) -> None:
    """A checkpoint that carries its own config: {"config": the `model:` section, "members": K,
    "state_dict"} (the physics branch's geometry and the training poses are buffers of the state)."""
    members = getattr(model, "n_members", 1)
    torch.save({"config": dict(cfg), "members": members, "state_dict": model.state_dict()}, path)


def load_model(path) -> BoTER | Ensemble:
    """The trained BoTER or Ensemble of a checkpoint (save_model; weights_only=True), in eval mode.
    Needs no params: the checkpoint says how to build it, its state holds the geometry."""
    ckpt = torch.load(path, weights_only=True, map_location="cpu")     # saved from the CPU; loads anywhere
    state = ckpt["state_dict"]
    geometry = {k: state[f"physics.{k}"] for k in RIGID_KEYS + MAP_KEYS if f"physics.{k}" in state}
    members = [make_model(ckpt["config"], geometry) for _ in range(ckpt["members"])]
    model = members[0] if len(members) == 1 else Ensemble(members)
    model.load_state_dict(state)
    model.config = ckpt["config"]
    return model.eval()

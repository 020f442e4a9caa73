"""The checkpoint: a trained model saved with its own config, and built back from it alone.

    make_model(cfg, geometry, kind)   BoTER (the `model:` section) or the DNN baseline, seeded
    save_model(model, path, cfg)      {"config", "members", "state_dict"} (torch.save)
    load_model(path)                  the model of a checkpoint, in eval mode; needs no params
"""
import torch

from pipeline.lib.learning.model import DNN, BoTER, Ensemble, check_config
from pipeline.lib.project.writing import write_by
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
    ckpt = {"config": dict(cfg), "members": members, "state_dict": model.state_dict()}
    write_by(path, lambda p: torch.save(ckpt, p))                  # whole or not at all


def load_model(path) -> BoTER | Ensemble:
    """The trained BoTER or Ensemble of a checkpoint (save_model; weights_only=True), in eval mode.
    Needs no params: the checkpoint says how to build it, its state holds the geometry."""
    try:
        ckpt = torch.load(path, weights_only=True, map_location="cpu")     # saved from the CPU; loads anywhere
    except (FileNotFoundError, IsADirectoryError, PermissionError):
        raise                                                                # OSErrors name the file
    except Exception as e:                 # truncated, not a torch file, unpickling refused: one line, the file
        raise ValueError(f"{path}: not a readable model checkpoint (truncated or corrupt?): "
                         f"{type(e).__name__}: {' '.join(str(e).split())[:200]}") from None
    if not (isinstance(ckpt, dict) and {"config", "members", "state_dict"} <= set(ckpt)):
        raise ValueError(f"{path}: not a model checkpoint: expected {{config, members, state_dict}} (save_model), "
                         f"got {sorted(ckpt) if isinstance(ckpt, dict) else type(ckpt).__name__}")
    state = ckpt["state_dict"]
    geometry = {k: state[f"physics.{k}"] for k in RIGID_KEYS + MAP_KEYS if f"physics.{k}" in state}
    try:
        members = [make_model(ckpt["config"], geometry) for _ in range(ckpt["members"])]
        model = members[0] if len(members) == 1 else Ensemble(members)
        model.load_state_dict(state)
    except (KeyError, TypeError, ValueError, RuntimeError) as e:   # its config and its weights disagree
        raise ValueError(f"{path}: the checkpoint's config does not build its weights: {type(e).__name__}: "
                         f"{' '.join(str(e).split())[:300]}") from None
    model.config = ckpt["config"]
    return model.eval()

"""BoTER: the eq. 4 mask exactly, the mask really blocking attention, shapes, config checks, the fade."""
import numpy as np
import pytest
import torch

from pipeline.lib.learning.model import (Ensemble, BODY_MASK, BoTER, attention_mask, check_config,
                                         encoder_for_export)
from pipeline.lib.learning.workspace import nearest_distance
from pipeline.lib.robot.kinematics import nominal_geometry
from pipeline.lib.robot.robots import nominal_robot

G = nominal_geometry(nominal_robot("ur5"))
SMALL = dict(d_model=12, n_layer=1, n_head=2, d_hidden=16, head="resnet", encoder=True, alpha0=0.1,
             dropout=0.0, fade_to=None)
CFG = {"d_model": 126, "n_layer": 4, "n_head": 9, "d_hidden": 512, "mask": "spi",
       "head": "resnet", "physics": "nominal", "fade_to": 2.0}


def test_spi_mask_is_eq4():
    expected = torch.tensor([[0, 0, 0, 0, 0, 0],
                             [0, 0, 0, 0, 0, 0],
                             [0, 0, 0, 0, 0, 0],
                             [1, 1, 0, 0, 0, 0],
                             [1, 1, 1, 0, 0, 0],
                             [1, 1, 1, 0, 0, 0]], dtype=torch.bool)
    assert torch.equal(attention_mask("spi"), expected)
    assert attention_mask("none") is None
    body = attention_mask("body")
    assert body.tolist() == [[bool(v) for v in r] for r in BODY_MASK]
    assert body.sum().item() == 20 and torch.equal(body, body.T)   # eq. 43: symmetric band


def test_mask_blocks_attention_from_joint_4_to_joints_1_2():
    torch.manual_seed(0)
    m = BoTER(G, mask="spi", **SMALL).eval()
    q = torch.randn(4, 6, dtype=torch.float64, requires_grad=True)
    x = m.encoder(m.embed(q.float()), mask=m.mask)         # (4, 6, d), one layer
    (x[:, 3] * torch.randn(12)).sum().backward()           # token of joint 4 (LayerNorm'd: project)
    assert q.grad[:, :2].abs().max().item() == 0.0         # masked: joints 1, 2 unseen
    assert q.grad[:, 2:].abs().min().item() > 0.0
    maps = m.attention_maps(q.detach())                    # (layers, B, heads, 6, 6)
    assert maps.shape == (1, 4, 2, 6, 6)
    assert maps[0, :, :, 3, :2].abs().max().item() == 0.0
    torch.testing.assert_close(maps.sum(-1), torch.ones_like(maps.sum(-1)))


def test_forward_fuses_physics_and_alpha_delta():
    torch.manual_seed(0)
    for kw in ({}, {"encoder": False}, {"head": "linear"}, {"mask": "body"}, {"mask": "none"}):
        m = BoTER(G, **{"mask": "spi", **SMALL, **kw}).eval()
        q = torch.randn(5, 6, dtype=torch.float64)
        p, p_th = m(q)
        assert p.shape == (5, 3) and p.dtype == torch.float64
        torch.testing.assert_close(p - p_th, m.delta(q))
    with torch.no_grad():
        m.alpha.zero_()
    torch.testing.assert_close(m(q)[0], m(q)[1])           # α = 0: pure physics


@pytest.mark.parametrize("change, message", [
    ({"n_head": 8}, "n_head=8 does not divide d_model=126"),
    ({"mask": "causal"}, "unknown mask 'causal'"),
    ({"head": "mlp"}, "unknown head 'mlp'"),
])                                 # a single value's range: config.RULES (tests/test_params.py)
def test_invalid_configs_stop_with_a_clear_message(change, message):
    with pytest.raises(ValueError, match=message):
        check_config({**CFG, **change})
    check_config(CFG)


def test_correction_fades_away_from_the_training_poses():
    """Within the workspace radius the full correction, beyond fade_to radii the physics alone,
    linear between; the training poses travel in the state dict (and size it on load)."""
    torch.manual_seed(0)
    m = BoTER(G, mask="spi", **{**SMALL, "fade_to": 2.0}).eval()
    train = np.zeros((3, 6))
    train[:, 0] = [0.0, 10.0, 20.0]                                  # deg, along joint 1
    m.fade.fit(train, radius_deg=10.0)
    q = np.zeros((5, 6))
    q[:, 0] = [10.0, 25.0, 35.0, 45.0, -170.0]                       # 0, 0.5, 1.5, 2.5 and 17 radii away
    q[:, 5] = 90.0                                                   # joint 6 is not part of the distance
    qt = torch.as_tensor(np.radians(q))
    w = m.fade(qt)[:, 0].numpy()
    np.testing.assert_allclose(w, [1.0, 1.0, 0.5, 0.0, 0.0], atol=1e-12)
    full = BoTER(G, mask="spi", **SMALL).eval()
    full.load_state_dict({k: v for k, v in m.state_dict().items() if not k.startswith("fade.")}, strict=False)
    torch.testing.assert_close(m.delta(qt), full.delta(qt) * torch.as_tensor(w)[:, None])
    p, p_th = m(qt)
    torch.testing.assert_close(p[3:], p_th[3:], rtol=0, atol=0)      # far away: the physics, exactly
    again = BoTER(G, mask="spi", **{**SMALL, "fade_to": 2.0})
    again.load_state_dict(m.state_dict())
    torch.testing.assert_close(again.eval()(qt)[0], p)
    m.train()                                                        # training sees the raw correction
    torch.testing.assert_close(m.delta(qt), full.train().delta(qt))


def test_ensemble_batched_prediction_equals_its_members_averaged_one_by_one():
    members = []
    for k in range(3):
        torch.manual_seed(k)
        m = BoTER(G, mask="spi", **{**SMALL, "fade_to": 2.0, "n_layer": 2})
        m.fade.fit(np.array([[0.0, -90, 90, -90, 90, 0], [90.0, -90, 90, -90, 90, 0]]), radius_deg=100.0)
        members.append(m.eval())
    ens = Ensemble(members).eval()
    q = torch.as_tensor(np.radians(np.random.default_rng(0).uniform(-120, 120, (9, 6))))
    with torch.no_grad():
        p, p_th = ens(q)
        one_by_one = torch.stack([m(q)[0] for m in members]).mean(0)
        torch.testing.assert_close(p, one_by_one, rtol=0, atol=1e-6)           # mm (float32 network)
        torch.testing.assert_close(p_th, members[0](q)[1], rtol=0, atol=0)
        spread = torch.stack([m.delta(q) for m in members]).std(0)
    assert spread.max() > 1e-3                                                  # the members do differ
    assert 0 < (ens.fade(q) == 1).sum() < len(q)                               # some inside, some faded
    # its state dict loads into a fresh ensemble of untrained members and predicts the same
    again = []
    for k in range(3):
        torch.manual_seed(10 + k)
        again.append(BoTER(G, mask="spi", **{**SMALL, "fade_to": 2.0, "n_layer": 2}))
    fresh = Ensemble(again)
    fresh.load_state_dict(ens.state_dict())
    with torch.no_grad():
        torch.testing.assert_close(fresh.eval()(q)[0], p, rtol=0, atol=0)


@pytest.mark.parametrize("mask", ["spi", "body", "none"])
def test_the_encoder_for_export_computes_what_the_module_computes(mask):
    """The export's leaner encoder (fewer ONNX nodes) against nn.TransformerEncoder, on the paper's
    size and a batch of poses: the same numbers to float32 rounding, the mask obeyed."""
    torch.manual_seed(0)
    m = BoTER(G, mask=mask, **{**SMALL, "d_model": 126, "n_layer": 4, "n_head": 9}).eval()
    x = m.embed(torch.as_tensor(np.radians(np.random.default_rng(1).uniform(-170, 170, (17, 6)))).float())
    with torch.no_grad():
        want = m.encoder(x, mask=m.mask, is_causal=False)
        got = encoder_for_export(m.encoder, x, m.mask)
    assert want.abs().max() > 0.1
    torch.testing.assert_close(got, want, rtol=0, atol=2e-5)


def test_nearest_distance_is_the_same_in_numpy_and_torch():
    """The workspace guard (numpy arrays) and the model's fade (tensors) measure one distance: wrapped over
    joints 1-5, by hand on two poses, and the two backends agree on many, leave-one-out included."""
    ref = np.array([[0.0, -90, 90, -90, 90, 0], [179.0, 0, 0, 0, 0, 0]])
    q = np.array([[3.0, -86, 90, -90, 90, 120],              # 3 and 4 deg off the first (joint 6 not counted)
                  [-179.0, 0, 0, 0, 0, 0]])                  # 2 deg off the second across ±180
    np.testing.assert_allclose(nearest_distance(q, ref), [5.0, 2.0], atol=1e-12)
    rng = np.random.default_rng(3)
    a, b = rng.uniform(-360, 360, (300, 6)), rng.uniform(-360, 360, (500, 6))
    in_torch = nearest_distance(torch.as_tensor(a), torch.as_tensor(b)).numpy()
    np.testing.assert_allclose(nearest_distance(a, b, chunk=64), in_torch, rtol=0, atol=1e-10)
    np.testing.assert_allclose(nearest_distance(b, b, leave_one_out=True),
                               nearest_distance(torch.as_tensor(b), torch.as_tensor(b), leave_one_out=True).numpy(),
                               rtol=0, atol=1e-10)
    assert nearest_distance(b, b, leave_one_out=True).min() > 0

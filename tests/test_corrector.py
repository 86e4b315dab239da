"""Correctors: zero-init identity, pose gradient stop, SH0 vs all SH, disabled, dims, first-layer split."""

from __future__ import annotations

import pytest
import torch

from framework.geometry import quat_to_rotmat
from framework.model.gaussian_init import random_in_box
from framework.registry import REGISTRIES
from framework.types import Gaussians

P = 17 * 3


def build(name, **kw):
    from framework.plugins import load_plugins

    load_plugins()
    c = REGISTRIES["corrector"].build(name, **kw)
    c.bind(P)
    return c


def gaussians(n=64) -> Gaussians:
    g = random_in_box(torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), n, seed=0)
    return g.replace(sh=torch.randn(g.sh.shape) * 0.2, quats=torch.randn(n, 4))


def randomise_head(c):
    torch.manual_seed(1)
    with torch.no_grad():
        c.head.weight.normal_(0, 0.1)
        c.head.bias.normal_(0, 0.1)


@pytest.mark.parametrize("name", ["latent", "posenc"])
def test_zero_init_is_identity(name):
    g, c = gaussians(), build(name)
    out = c(g, torch.randn(P))
    for k in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert torch.equal(getattr(out, k), getattr(g, k)), k


def test_feature_dims():
    assert build("latent").feature_in.in_features == 9
    assert build("posenc").feature_in.in_features == 21
    c = build("latent")
    assert c.pose_in.in_features == P and c.head.out_features == 11
    # 4 layers: the first is split into two Linear modules (pose part, feature part)
    assert sum(isinstance(m, torch.nn.Linear) for m in c.modules()) == 5


def test_pose_is_gradient_stopped_and_latents_get_gradients():
    c = build("latent")
    randomise_head(c)
    g = gaussians()
    g = g.replace(latents=g.latents.clone().requires_grad_())
    pose = torch.randn(P, requires_grad=True)
    out = c(g, pose)
    (out.opacity_logits.sum() + out.sh.sum() + out.log_scales.sum()).backward()
    assert pose.grad is None
    assert g.latents.grad is not None and g.latents.grad.abs().sum() > 0
    assert c.pose_in.weight.grad.abs().sum() > 0


def test_first_layer_split_equals_concatenated_mlp():
    c = build("latent")
    randomise_head(c)
    g, pose = gaussians(), torch.randn(P)
    W = torch.cat([c.pose_in.weight, c.feature_in.weight], dim=1)  # the unsplit first layer
    x = torch.cat([pose.expand(g.num, P), g.latents], dim=1)
    h = torch.relu(x @ W.T + c.feature_in.bias)
    for layer in c.trunk:
        h = layer(h)
    d = c.head(h)
    out = c(g, pose)
    assert torch.allclose(out.opacity_logits, g.opacity_logits + d[:, 0], atol=1e-6)
    assert torch.allclose(out.log_scales, g.log_scales + d[:, 1:4], atol=1e-6)
    dq = d[:, 4:8] + torch.tensor([1.0, 0, 0, 0])
    assert torch.allclose(quat_to_rotmat(out.quats), quat_to_rotmat(dq) @ quat_to_rotmat(g.quats), atol=1e-5)
    assert torch.allclose(out.sh[:, 0], g.sh[:, 0] + d[:, 8:11], atol=1e-6)
    assert torch.equal(out.means, g.means)


@pytest.mark.parametrize("rows", [None, [3, 10, 11, 40]])
def test_inference_layers_equal_the_plain_ones(rows):
    """Without gradients F_a runs oneDNN's fused linear + bias + ReLU (`corrector_mlp._fuses_layers`); its residuals
    must equal the plain nn.Linear layers' (taken with gradients on) to float32 rounding, a partial fold's rows
    included. Every layer is randomised, so a wrong bias, a missing ReLU or a layer skipped would show."""
    from framework.model import corrector_mlp

    c = build("latent")
    torch.manual_seed(2)
    with torch.no_grad():
        for p in c.parameters():
            p.normal_(0, 0.3)
    if rows is not None:
        c.active_rows = torch.tensor(rows)
    g, pose = gaussians(300), torch.randn(P)
    assert corrector_mlp._FUSED_LINEAR_AVAILABLE  # the CPU build CI installs has it: the fused path is tested
    with torch.no_grad():
        assert corrector_mlp._fuses_layers(g.latents, c.execution)
        fused = c.residuals(g, pose)
    with torch.enable_grad():
        assert not corrector_mlp._fuses_layers(g.latents, c.execution)
        plain = c.residuals(g, pose).detach()
    assert fused.abs().max() > 0.1  # the layers do something
    torch.testing.assert_close(fused, plain, rtol=1e-5, atol=1e-5)  # float32: products summed in another order


def test_sh0_only_vs_all_sh():
    g, pose = gaussians(), torch.randn(P)
    c0, ca = build("latent"), build("latent", all_sh=True)
    randomise_head(c0)
    randomise_head(ca)
    o0, oa = c0(g, pose), ca(g, pose)
    assert torch.equal(o0.sh[:, 1:], g.sh[:, 1:]) and not torch.allclose(o0.sh[:, 0], g.sh[:, 0])
    assert ca.head.out_features == 8 + 16 * 3
    assert (oa.sh - g.sh).abs().amax(dim=(0, 2)).min() > 0  # every coefficient is corrected
    g1 = g.replace(sh=g.sh[:, :4])  # fewer stored coefficients than the corrector predicts
    assert ca(g1, pose).sh.shape == (g.num, 4, 3)


def test_disabled_returns_input_and_uses_no_params():
    c = build("posenc")
    randomise_head(c)
    c.enabled = False
    g = gaussians()
    g = g.replace(opacity_logits=g.opacity_logits.clone().requires_grad_())
    out = c(g, torch.randn(P))
    assert out is g
    out.opacity_logits.sum().backward()
    assert all(p.grad is None for p in c.parameters())


def test_none_corrector_and_errors():
    g = gaussians()
    assert build("none")(g, torch.randn(P)) is g
    from framework.plugins import load_plugins

    load_plugins()
    unbound = REGISTRIES["corrector"].build("latent")
    with pytest.raises(RuntimeError, match="bind"):
        unbound(g, torch.randn(P))
    with pytest.raises(ValueError, match="pose has 5 features"):
        build("latent")(g, torch.randn(5))
    with pytest.raises(ValueError, match="latents"):
        build("latent")(g.replace(latents=None), torch.randn(P))


def test_extreme_inputs_finite():
    c = build("latent")
    randomise_head(c)
    g = gaussians(32)
    g = g.replace(opacity_logits=torch.full((32,), 30.0).requires_grad_(), quats=torch.zeros(32, 4))
    out = c(g, torch.full((P,), 1e3))
    assert all(torch.isfinite(getattr(out, k)).all() for k in ("quats", "log_scales", "opacity_logits", "sh"))
    assert c(gaussians(1).index(torch.zeros(0, dtype=torch.long)), torch.randn(P)).num == 0

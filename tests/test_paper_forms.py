"""The three places where our model may differ from the paper's equations, each offered as an option: every form
against its closed form (float64, by hand)."""

from __future__ import annotations

import math

import pytest
import torch

from framework.plugins import load_plugins
from framework.registry import DEFORMERS, LOSSES
from framework.rig.lbs import apply_lbs
from framework.types import Cameras, FrameBatch, Gaussians, RenderOutput

load_plugins()
D64 = torch.float64


def _alpha_case() -> tuple[RenderOutput, FrameBatch]:
    alpha = torch.tensor([[[0.9, 0.2], [0.0, 0.6]], [[1.0, 1.0], [0.0, 0.0]]], dtype=D64)[..., None]  # [2, 2, 2, 1]
    mask = torch.tensor([[[1.0, 0.0], [0.0, 1.0]], [[1.0, 1.0], [0.0, 0.0]]], dtype=D64)
    boundary = torch.tensor([[[1.0, 1.0], [1.0, 0.0]], [[1.0, 1.0], [1.0, 1.0]]], dtype=D64)
    cams = Cameras(torch.eye(3).expand(2, 3, 3), torch.eye(4).expand(2, 4, 4), 2, 2)
    render = RenderOutput(rgb=torch.zeros(2, 2, 2, 3, dtype=D64), alpha=alpha, depth=None,
                          means2d=torch.zeros(2, 0, 2), radii=torch.zeros(2, 0))  # fmt: skip
    batch = FrameBatch(image=torch.zeros(2, 2, 2, 3, dtype=D64), mask=mask, boundary=boundary, cameras=cams,
                       frame=torch.zeros(2, dtype=torch.long))  # fmt: skip
    return render, batch


@pytest.mark.parametrize("norm", ["l1", "l2"])
def test_alpha_loss_forms(norm: str):
    """Image 0: errors 0.1, 0.2, 0 and (0.4 under M_b = 0, ignored); image 1 is perfect.
    l1 (ours): (0.1 + 0.2) / 8 pixels. l2 (paper eq. 7): per image sqrt(0.1^2 + 0.2^2) / sqrt(4), batch mean."""
    render, batch = _alpha_case()
    alpha = render.alpha.clone().requires_grad_(True)
    out = LOSSES.build("alpha", norm=norm)(RenderOutput(render.rgb, alpha, None, render.means2d, render.radii),
                                           batch, {})  # fmt: skip
    expected = 0.3 / 8 if norm == "l1" else (math.sqrt(0.01 + 0.04) / 2 + 0.0) / 2
    assert out.item() == pytest.approx(expected, rel=1e-12)
    out.backward()
    assert torch.isfinite(alpha.grad).all()  # image 1 has zero error: the norm's gradient there is 0, not NaN
    assert (alpha.grad[1] == 0).all() and alpha.grad[0, 1, 1, 0] == 0  # M_b = 0 pixel


def _two_bone_case():
    """Bone 0 still, bone 1 turned 90 degrees about z and moved; a Gaussian weighted half and half."""
    T = torch.eye(4, dtype=D64).repeat(2, 1, 1)
    T[1, :3, :3] = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=D64)
    T[1, :3, 3] = torch.tensor([0.2, -0.4, 0.6], dtype=D64)
    x = torch.tensor([[0.3, 0.1, -0.2]], dtype=D64)
    g = Gaussians(means=x, quats=torch.tensor([[1.0, 0, 0, 0]], dtype=D64), log_scales=torch.zeros(1, 3, dtype=D64),
                  opacity_logits=torch.zeros(1, dtype=D64), sh=torch.zeros(1, 1, 3, dtype=D64))  # fmt: skip
    return g, torch.tensor([[0.5, 0.5]], dtype=D64), T


def test_centres_blended_and_rigid_forms():
    """A = (I + Rz(90)) / 2 = cos(45) Rz(45) in the xy plane (z kept), so its polar rotation is Rz(45);
    t = (0.1, -0.2, 0.3). blended (ours): A x + t. rigid (paper eq. 4): Rz(45) x + t."""
    g, w, T = _two_bone_case()
    x, y, z = 0.3, 0.1, -0.2
    t = torch.tensor([0.1, -0.2, 0.3], dtype=D64)
    blended = torch.tensor([(x - y) / 2, (x + y) / 2, z], dtype=D64) + t
    c = math.sqrt(0.5)
    rigid = torch.tensor([c * (x - y), c * (x + y), z], dtype=D64) + t
    torch.testing.assert_close(apply_lbs(g, w, T, centres="blended").means[0], blended, atol=1e-12, rtol=0)
    torch.testing.assert_close(apply_lbs(g, w, T, centres="rigid").means[0], rigid, atol=1e-9, rtol=0)
    with pytest.raises(ValueError, match="centres"):
        apply_lbs(g, w, T, centres="dual_quaternion")


@pytest.fixture(scope="module")
def body():
    from plugins.body.procedural import ProceduralBody

    return ProceduralBody(segments=8)


def _residual_deformer(body, residual: str, bias: torch.Tensor, tmp_path, monkeypatch):
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(tmp_path))
    d = DEFORMERS.build("lbs_residual", grid_resolution=10, residual=residual)
    lo, hi = body.rest_vertices.min(0).values, body.rest_vertices.max(0).values
    d.bind(body, torch.stack([lo - 0.1, hi + 0.1]))
    with torch.no_grad():  # F_dw(x) = bias everywhere: the last layer's weights stay zero
        d.mlp[-1].bias.copy_(bias)
    return d


@pytest.mark.parametrize("residual", ["softmax", "additive"])
def test_weight_residual_forms(body, residual: str, tmp_path, monkeypatch):
    """With F_dw(x) = b: additive (paper) w = w0 + b; softmax (ours) w = (w0 + eps) e^b / sum_k (w0 + eps)_k e^b_k."""
    J = body.num_joints
    bias = torch.linspace(-0.5, 0.7, J)
    d = _residual_deformer(body, residual, bias, tmp_path, monkeypatch)
    points = body.rest_vertices[::97]  # [Q, 3]
    d.enabled = False
    w0 = d.weights(points).double()  # the grid weights the residual starts from
    d.enabled = True
    w = d.weights(points).double()
    b = bias.double()
    if residual == "additive":
        expected = w0 + b
    else:
        u = (w0 + d.eps) * torch.exp(b)
        expected = u / u.sum(-1, keepdim=True)
    torch.testing.assert_close(w, expected, atol=2e-6, rtol=0)  # float32 evaluation
    with pytest.raises(ValueError, match="residual"):
        DEFORMERS.build("lbs_residual", residual="exp")

"""The paper's equation forms (paper_full's defaults) and the project's own forms (options), each against a closed
form or an independent reference in float64: blend weights, Gaussian centres, the alpha loss, D-SSIM and L_w."""

from __future__ import annotations

import copy
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
    render = RenderOutput(
        rgb=torch.zeros(2, 2, 2, 3, dtype=D64),
        alpha=alpha,
        depth=None,
        means2d=torch.zeros(2, 0, 2),
        radii=torch.zeros(2, 0),
    )
    batch = FrameBatch(
        image=torch.zeros(2, 2, 2, 3, dtype=D64),
        mask=mask,
        boundary=boundary,
        cameras=cams,
        frame=torch.zeros(2, dtype=torch.long),
    )
    return render, batch


@pytest.mark.parametrize(
    ("norm", "expected"),
    [
        ("mse", (0.1**2 + 0.2**2) / 8),  # paper_full: eq. 7's norm squared, per pixel
        ("rms", (math.sqrt(0.1**2 + 0.2**2) / 2 + 0.0) / 2),  # the norm per image / sqrt(H W), batch mean
        ("l1", (0.1 + 0.2) / 8),  # the project's form
    ],
)
def test_alpha_loss_forms(norm: str, expected: float):
    """Image 0: errors 0.1, 0.2, 0 and (0.4 under M_b = 0, ignored); image 1 is perfect."""
    render, batch = _alpha_case()
    alpha = render.alpha.clone().requires_grad_(True)
    out = LOSSES.build("alpha", norm=norm)(
        RenderOutput(render.rgb, alpha, None, render.means2d, render.radii), batch, {}
    )
    assert out.item() == pytest.approx(expected, rel=1e-12)
    out.backward()
    assert torch.isfinite(alpha.grad).all()  # image 1 has zero error: the norm's gradient there is 0, not NaN
    assert (alpha.grad[1] == 0).all() and alpha.grad[0, 1, 1, 0] == 0  # M_b = 0 pixel
    # without M_b the masked pixel's error (0.6 - 1 = -0.4) counts
    free = LOSSES.build("alpha", norm=norm, boundary=False)(render, batch, {}).item()
    assert free > out.item() + 1e-3


def test_alpha_loss_default_is_the_papers_reading():
    render, batch = _alpha_case()
    assert LOSSES.build("alpha")(render, batch, {}).item() == pytest.approx(0.05 / 8, rel=1e-12)


def _constant_pair(a: float, b: float, size: int = 13) -> tuple[RenderOutput, FrameBatch]:
    cams = Cameras(torch.eye(3)[None], torch.eye(4)[None], size, size)
    render = RenderOutput(
        rgb=torch.full((1, size, size, 3), a, dtype=D64),
        alpha=torch.zeros(1, size, size, 1),
        depth=None,
        means2d=torch.zeros(1, 0, 2),
        radii=torch.zeros(1, 0),
    )
    batch = FrameBatch(
        image=torch.full((1, size, size, 3), b, dtype=D64),
        mask=torch.zeros(1, size, size),
        boundary=torch.ones(1, size, size),
        cameras=cams,
        frame=torch.zeros(1, dtype=torch.long),
    )
    return render, batch


@pytest.mark.parametrize(("a", "b"), [(0.3, 0.7), (0.05, 0.9), (0.5, 0.5)])
def test_dssim_is_one_minus_ssim_closed_form(a: float, b: float):
    """Two constant images: no variance, so SSIM = (2 a b + C1) / (a^2 + b^2 + C1) exactly (C1 = 0.01^2). The paper's
    D-SSIM (3DGS's code) is 1 - SSIM; the project's earlier form is half of it."""
    c1 = 0.01**2
    ssim = (2 * a * b + c1) / (a * a + b * b + c1)
    render, batch = _constant_pair(a, b)
    assert LOSSES.build("dssim")(render, batch, {}).item() == pytest.approx(1 - ssim, abs=1e-8)  # blur rounding
    assert LOSSES.build("dssim", form="half")(render, batch, {}).item() == pytest.approx((1 - ssim) / 2, abs=1e-8)
    with pytest.raises(ValueError, match="form"):
        LOSSES.build("dssim", form="quarter")


def test_dssim_is_one_minus_kornia_ssim():
    """Random non-square images: 1 - the mean of kornia's SSIM map, and twice kornia's own ssim_loss (which is
    (1 - SSIM) / 2)."""
    from kornia.losses import ssim_loss
    from kornia.metrics import ssim

    g = torch.Generator().manual_seed(7)
    rgb, image = (torch.rand(2, 19, 23, 3, generator=g, dtype=D64) for _ in range(2))
    cams = Cameras(torch.eye(3).expand(2, 3, 3), torch.eye(4).expand(2, 4, 4), 23, 19)
    render = RenderOutput(
        rgb=rgb, alpha=torch.zeros(2, 19, 23, 1), depth=None, means2d=torch.zeros(2, 0, 2), radii=torch.zeros(2, 0)
    )
    batch = FrameBatch(
        image=image,
        mask=torch.zeros(2, 19, 23),
        boundary=torch.ones(2, 19, 23),
        cameras=cams,
        frame=torch.zeros(2, dtype=torch.long),
    )
    a, b = rgb.permute(0, 3, 1, 2), image.permute(0, 3, 1, 2)
    ours = LOSSES.build("dssim", compiled=False)(render, batch, {}).item()
    assert ours == pytest.approx(1 - ssim(a, b, 11, max_val=1.0).mean().item(), abs=1e-12)
    assert ours == pytest.approx(2 * ssim_loss(a, b, 11, max_val=1.0).item(), abs=1e-12)
    assert LOSSES.build("dssim")(render, batch, {}).item() == pytest.approx(ours, abs=1e-10)  # compiled loops


def test_weight_std_reductions():
    """Eq. 8's Sum_i: paper_full reads it as a mean over Gaussians (its weight does not grow with N); sum: an option."""
    render, batch = _alpha_case()
    std = torch.tensor([0.1, 0.4, 0.0, 0.3], dtype=D64)
    assert LOSSES.build("weight_std")(render, batch, {"weight_std": std}).item() == pytest.approx(0.2, rel=1e-12)
    summed = LOSSES.build("weight_std", reduction="sum")(render, batch, {"weight_std": std})
    assert summed.item() == pytest.approx(0.8, rel=1e-12)


def _two_bone_case():
    """Bone 0 still, bone 1 turned 90 degrees about z and moved; a Gaussian weighted half and half."""
    T = torch.eye(4, dtype=D64).repeat(2, 1, 1)
    T[1, :3, :3] = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=D64)
    T[1, :3, 3] = torch.tensor([0.2, -0.4, 0.6], dtype=D64)
    x = torch.tensor([[0.3, 0.1, -0.2]], dtype=D64)
    g = Gaussians(
        means=x,
        quats=torch.tensor([[1.0, 0, 0, 0]], dtype=D64),
        log_scales=torch.zeros(1, 3, dtype=D64),
        opacity_logits=torch.zeros(1, dtype=D64),
        sh=torch.zeros(1, 1, 3, dtype=D64),
    )
    return g, torch.tensor([[0.5, 0.5]], dtype=D64), T


def test_centres_rigid_and_blended_forms():
    """A = (I + Rz(90)) / 2 = cos(45) Rz(45) in the xy plane (z kept), so its polar rotation is Rz(45);
    T = t = (0.1, -0.2, 0.3). rigid (paper eq. 4, paper_full): Rz(45) x + T. blended (the project's): A x + t."""
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


def _random_rotation(g: torch.Generator, max_angle: float = 1.2) -> torch.Tensor:
    """exp of a random skew matrix: a turn of up to `max_angle` radians about a random axis (bones of one blend turn by
    comparable amounts, so A = sum_k w_k R_k keeps a positive determinant and a unique rotation factor)."""
    axis = torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=D64), dim=0)
    k = axis * max_angle * torch.rand((), generator=g, dtype=D64)
    skew = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], dtype=D64)
    return torch.linalg.matrix_exp(skew)


def test_rigid_centres_against_a_float64_polar_reference():
    """Many Gaussians, three bones with random rotations and translations, random partition-of-unity weights: the
    paper's x' = R x + T with R the rotation factor of A = sum_k w_k R_k from an SVD (U V^T, float64) and
    T = sum_k w_k t_k, against `apply_lbs` (its own polar iteration)."""
    g = torch.Generator().manual_seed(11)
    J, N = 3, 64
    T = torch.eye(4, dtype=D64).repeat(J, 1, 1)
    for k in range(J):
        T[k, :3, :3] = _random_rotation(g)
        T[k, :3, 3] = torch.randn(3, generator=g, dtype=D64)
    w = torch.rand(N, J, generator=g, dtype=D64)
    w = w / w.sum(-1, keepdim=True)
    means = torch.randn(N, 3, generator=g, dtype=D64)
    gs = Gaussians(
        means=means,
        quats=torch.tensor([[1.0, 0, 0, 0]], dtype=D64).repeat(N, 1),
        log_scales=torch.zeros(N, 3, dtype=D64),
        opacity_logits=torch.zeros(N, dtype=D64),
        sh=torch.zeros(N, 1, 3, dtype=D64),
    )
    A = torch.einsum("nk,kij->nij", w, T[:, :3, :3])
    t = w @ T[:, :3, 3]
    u, _, vh = torch.linalg.svd(A)
    R = u @ vh
    assert (torch.det(R) > 0).all()
    expected = torch.einsum("nij,nj->ni", R, means) + t
    torch.testing.assert_close(apply_lbs(gs, w, T, centres="rigid").means, expected, atol=1e-9, rtol=0)
    assert (apply_lbs(gs, w, T, centres="blended").means - expected).abs().max() > 1e-3  # the forms differ here


@pytest.fixture(scope="module")
def body():
    from plugins.body.procedural import ProceduralBody

    return ProceduralBody(segments=8)


def _residual_deformer(body, residual: str, bias: torch.Tensor, tmp_path, monkeypatch, **kwargs):
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(tmp_path))
    d = DEFORMERS.build("lbs_residual", grid_resolution=10, residual=residual, **kwargs)
    lo, hi = body.rest_vertices.min(0).values, body.rest_vertices.max(0).values
    d.bind(body, torch.stack([lo - 0.1, hi + 0.1]))
    with torch.no_grad():  # F_dw(x) = bias everywhere: the last layer's weights stay zero
        d.mlp[-1].bias.copy_(bias)
    return d


def _expected_weights(residual: str, w0: torch.Tensor, b: torch.Tensor, eps: float) -> torch.Tensor:
    if residual == "additive":  # the paper, as written
        return w0 + b
    if residual == "additive_normalised":
        u = (w0 + b).clamp_min(0)
        return u / u.sum(-1, keepdim=True)
    u = (w0 + eps) * torch.exp(b)  # softmax(log(w0 + eps) + b)
    return u / u.sum(-1, keepdim=True)


@pytest.mark.parametrize("residual", ["additive", "additive_normalised", "softmax"])
def test_weight_residual_forms(body, residual: str, tmp_path, monkeypatch):
    """With F_dw(x) = b: additive (paper) w = w0 + b; additive_normalised max(w0 + b, 0) / sum; softmax (the project's)
    w = (w0 + eps) e^b / sum_k (w0 + eps)_k e^b_k. Through `weights` (torch) and through `smooth_weights`, the path
    training takes (compiled loops on the CPU where the form has them)."""
    J = body.num_joints
    bias = torch.linspace(-0.5, 0.7, J)
    d = _residual_deformer(body, residual, bias, tmp_path, monkeypatch)
    points = body.rest_vertices[::97]  # [Q, 3]
    d.enabled = False
    w0 = d.weights(points).double()  # the grid weights the residual starts from
    d.enabled = True
    expected = _expected_weights(residual, w0, bias.double(), d.eps)
    torch.testing.assert_close(d.weights(points).double(), expected, atol=2e-6, rtol=0)  # float32 evaluation
    seven = points.unsqueeze(1).expand(-1, 7, -1).contiguous()  # the centre repeated as the six L_w points
    centre, lw = d.smooth_weights(seven)
    torch.testing.assert_close(centre.double(), expected, atol=2e-6, rtol=0)
    torch.testing.assert_close(lw, torch.zeros_like(lw), atol=1e-6, rtol=0)  # no spread over identical points
    if residual == "additive":
        assert (expected.sum(-1) - 1).abs().min() > 0.1  # as written, w0 + F_dw is not renormalised
    else:
        torch.testing.assert_close(expected.sum(-1), torch.ones(len(points), dtype=D64))
    with pytest.raises(ValueError, match="residual"):
        DEFORMERS.build("lbs_residual", residual="exp")


def test_additive_weights_follow_a_non_constant_residual(body, tmp_path, monkeypatch):
    """A random last layer (F_dw varies over space): the weights are the grid weights plus the MLP's output at each
    point, unchanged (float64 reference from the MLP's own layers)."""
    from framework.model.posenc import normalize_to_bounds, posenc

    d = _residual_deformer(body, "additive", torch.zeros(body.num_joints), tmp_path, monkeypatch)
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        d.mlp[-1].weight.copy_(0.3 * torch.randn(d.mlp[-1].weight.shape, generator=g))
    points = body.rest_vertices[::61]
    d.enabled = False
    w0 = d.weights(points).double()
    d.enabled = True
    x = posenc(normalize_to_bounds(points.double(), d.field.bounds.double()), d.num_freqs)
    x = copy.deepcopy(d.mlp).double()(x)
    assert x.abs().max() > 0.05  # the residual does something
    torch.testing.assert_close(d.weights(points).double(), w0 + x, atol=5e-6, rtol=0)

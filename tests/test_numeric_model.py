"""Numerical extremes of the model's learnable parts and losses (hypothesis): the appearance correctors (F_a) and
every loss term and their weighted composite.

References are float64: the corrector deep-copied to float64 and fed the same (float32-rounded) inputs, and the loss
formulas written out in numpy (the SSIM map of tests/test_losses.py). Tolerances (float32): correctors 1e-4 relative
to the output's scale (5e-2 for posenc beyond 10 extents, where float32 sin/cos arguments 2^k pi x lose digits);
losses 1e-5 relative plus 1e-6 absolute (DSSIM 1e-5 absolute, as it divides
variances of float32 blurs).
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from test_losses import _ssim_map_mirror

from framework.guards import WEIGHT_VAR_MIN
from framework.model.losses import CompositeLoss
from framework.plugins import load_plugins
from framework.registry import CORRECTORS, LOSSES
from framework.rig.lbs import weight_std
from framework.testing.properties import all_finite, relative_error
from framework.types import Cameras, FrameBatch, Gaussians, RenderOutput

load_plugins()
J = 24
D64 = torch.float64


# ---------------------------------------------------------------------------------------------------- correctors
@st.composite
def corrector_cases(draw: st.DrawFn):
    """Poses in a human range, far outside it (10..1000 rad) or zero; latent codes and positions from 1e-6 to 1e3;
    quaternions of norm 0..1e3; opacity logits +-30; a trained-looking (random, non-zero) network."""
    kind = draw(st.sampled_from(["latent", "posenc"]))
    g = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    pose_kind = draw(st.sampled_from(["human", "far", "zero"]))
    n = 16
    direction = torch.nn.functional.normalize(torch.randn(J, 3, generator=g), dim=-1)
    pose = {
        "human": direction * torch.rand(J, 1, generator=g) * 2.5,
        "far": direction * torch.empty(J, 1).uniform_(10.0, 1000.0, generator=g),
        "zero": torch.zeros(J, 3),
    }[pose_kind]
    mag = draw(st.sampled_from([1e-6, 1.0, 10.0, 1e3]))
    gaussians = Gaussians(
        means=torch.randn(n, 3, generator=g) * mag,
        quats=torch.randn(n, 4, generator=g) * draw(st.sampled_from([0.0, 1e-20, 1e-3, 1.0, 1e3])),
        log_scales=torch.empty(n, 3).uniform_(math.log(1e-7), math.log(1e3), generator=g),
        opacity_logits=torch.tensor([-30.0, 30.0]).repeat(n // 2),
        sh=torch.randn(n, 16, 3, generator=g),
        latents=torch.randn(n, 9, generator=g) * mag,
    )
    return kind, pose_kind, mag, pose, gaussians, draw(st.booleans())


@given(case=corrector_cases())
def test_corrector_extremes(case) -> None:
    """Corrected Gaussians and every gradient are finite; they match the float64 network within 1e-4 of their scale
    (posenc beyond 10 extents: finite and bounded only, see the module docstring)."""
    kind, pose_kind, mag, pose, g32, all_sh = case
    corr = CORRECTORS.build(kind, hidden=32, layers=3, all_sh=all_sh)
    corr.bind(J * 3)
    with torch.no_grad():  # a trained network, not the zero-initialised head
        gen = torch.Generator().manual_seed(3)
        for p in corr.parameters():
            p.copy_(0.3 * torch.randn(p.shape, generator=gen))
    params = {k: v.clone().requires_grad_() for k, v in vars(g32).items() if isinstance(v, torch.Tensor)}
    out = corr(Gaussians(**params), pose)
    fields = ("opacity_logits", "log_scales", "quats", "sh")
    loss = sum(getattr(out, f).sum() for f in fields)
    loss.backward()
    assert all_finite(*(getattr(out, f) for f in fields)), f"{kind}/{pose_kind}"
    assert all_finite(*(p.grad for p in corr.parameters()), *(p.grad for p in params.values() if p.grad is not None))
    corr64 = copy.deepcopy(corr).double()
    g64 = Gaussians(**{k: v.detach().double() for k, v in params.items()})
    ref = corr64(g64, pose.double())
    # posenc beyond 10 extents: float32 sin/cos arguments 2^k pi x carry ~eps * 2^k pi |x| (~4e-3 at 1e3 extents)
    rtol = 1e-4 if kind == "latent" or mag <= 10.0 else 5e-2
    for f in fields:
        got, want = getattr(out, f).detach().double(), getattr(ref, f).detach()
        scale = float(want.abs().max()) + 1.0
        assert float((got - want).abs().max()) <= rtol * scale, f"{kind}/{pose_kind}/{f}"


# -------------------------------------------------------------------------------------------------------- losses
@st.composite
def loss_cases(draw: st.DrawFn):
    """Images of 1x1 to 16x16; renders that are black, white, uniform or far outside [0, 1] (1e3); masks and
    boundary bands that are empty, full or random."""
    h, w = draw(st.integers(1, 16)), draw(st.integers(1, 16))
    g = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    fill = draw(st.sampled_from(["uniform", "zeros", "ones", "huge", "tiny"]))
    rgb = {
        "uniform": torch.rand(1, h, w, 3, generator=g),
        "zeros": torch.zeros(1, h, w, 3),
        "ones": torch.ones(1, h, w, 3),
        "huge": 1e3 * torch.rand(1, h, w, 3, generator=g),
        "tiny": 1e-30 * torch.rand(1, h, w, 3, generator=g),
    }[fill]
    alpha = rgb.mean(-1, keepdim=True).clamp(0, 1)
    image = torch.rand(1, h, w, 3, generator=g) if draw(st.booleans()) else rgb.clamp(0, 1).clone()

    def mask(kind: str) -> torch.Tensor:
        return {
            "empty": torch.zeros(1, h, w),
            "full": torch.ones(1, h, w),
            "random": torch.rand(1, h, w, generator=g).round(),
        }[kind]

    kinds = st.sampled_from(["empty", "full", "random"])
    m, b = mask(draw(kinds)), mask(draw(kinds))
    var_kind = draw(st.sampled_from(["rigid", "tiny", "normal"]))
    weights6 = torch.softmax(torch.randn(50, 1, 8, generator=g).expand(50, 6, 8).clone(), -1)  # rigid: equal rows
    if var_kind != "rigid":
        weights6 = weights6 + {"tiny": 1e-7, "normal": 0.1}[var_kind] * torch.rand(50, 6, 8, generator=g)
    return f"{fill}/{h}x{w}/{var_kind}", rgb, alpha, image, m, b, weights6


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().double().numpy()


@given(case=loss_cases())
def test_loss_extremes(case) -> None:
    """Each loss term and the paper's weighted composite: finite values and gradients, equal to the float64 formula."""
    kind, rgb, alpha, image, mask, boundary, weights6 = case
    rgb, alpha, weights6 = (t.clone().requires_grad_() for t in (rgb, alpha, weights6))
    h, w = rgb.shape[1:3]
    cams = Cameras(torch.eye(3)[None], torch.eye(4)[None], w, h)
    render = RenderOutput(rgb=rgb, alpha=alpha, depth=None, means2d=torch.zeros(1, 0, 2), radii=torch.zeros(1, 0))
    batch = FrameBatch(image=image, mask=mask, boundary=boundary, cameras=cams, frame=torch.zeros(1, dtype=torch.long))
    std = weight_std(weights6)
    aux = {"weight_std": std}
    r, im, m, b = _np(rgb)[0], _np(image)[0], _np(mask)[0], _np(boundary)[0]
    win = min(11, 2 * min(h, w) - 1)
    ssim = [_ssim_map_mirror(r[..., c], im[..., c], window=win) for c in range(3)]
    var = _np(weights6).var(axis=1)
    expected = {
        "l1": (np.abs(r - im) * b[..., None]).mean(),
        "alpha": (((_np(alpha)[0, ..., 0] - m) * b) ** 2).mean(),  # eq. 7's norm squared per pixel
        "dssim": np.mean([1 - s for s in ssim]),  # 3DGS's 1 - SSIM
        "weight_std": np.where(var > WEIGHT_VAR_MIN, np.sqrt(var), 0.0).sum(-1).mean(),
    }
    values = {}
    for name, want in expected.items():
        got = LOSSES.build(name)(render, batch, aux)
        values[name] = got
        tol = 2e-5 if name == "dssim" else 1e-5 * abs(want) + 1e-6
        assert abs(float(got.detach()) - want) <= tol, f"{kind}: {name} {float(got.detach())} vs {want}"
    composite = CompositeLoss(
        {"l1": {"weight": 0.8}, "alpha": {"weight": 10.0}, "weight_std": {"weight": 0.2}, "dssim": {"weight": 0.2}}
    )
    total, terms = composite(render, batch, aux)
    want_total = 0.8 * expected["l1"] + 10 * expected["alpha"] + 0.2 * expected["weight_std"] + 0.2 * expected["dssim"]
    assert abs(float(total.detach()) - want_total) <= 1e-5 * abs(want_total) + 1e-5, kind
    total.backward()
    assert all_finite(total, rgb.grad, alpha.grad, weights6.grad), kind


def test_weight_std_guard_is_what_happens() -> None:
    """Variances at or below WEIGHT_VAR_MIN count as exactly zero (value and gradient), above it as sqrt(var)."""
    w6 = torch.zeros(3, 6, 2, dtype=D64)
    w6[0, 0, 0] = 2 * math.sqrt(WEIGHT_VAR_MIN)  # variance (5/36) x^2 = 0.56e-12 < WEIGHT_VAR_MIN: counted as 0
    w6[1, :3, 0] = 0.2  # variance 0.01
    w6 = w6.requires_grad_()
    std = weight_std(w6)
    std.sum().backward()
    assert float(std[0].detach()) == 0.0 and float(w6.grad[0].abs().max()) == 0.0
    assert float(std[1].detach()) == pytest.approx(0.1, rel=1e-12) and float(std[2].detach()) == 0.0
    assert all_finite(w6.grad)


@pytest.mark.parametrize("fill", [0.0, 1.0, 1e3])
def test_lpips_extremes(fill: float) -> None:
    """LPIPS of constant (black, white, 1e3) renders against a random image: finite value and gradient, and equal to
    the network in float64 (relative 1e-4)."""
    entry = LOSSES.entry("lpips")
    if entry.unavailable_reason() is not None:
        pytest.skip(entry.unavailable_reason())
    rgb = torch.full((1, 32, 32, 3), fill, requires_grad=True)
    image = torch.rand(1, 32, 32, 3, generator=torch.Generator().manual_seed(0))
    cams = Cameras(torch.eye(3)[None], torch.eye(4)[None], 32, 32)
    render = RenderOutput(rgb, rgb[..., :1], None, means2d=torch.zeros(1, 0, 2), radii=torch.zeros(1, 0))
    batch = FrameBatch(
        image=image,
        mask=torch.ones(1, 32, 32),
        boundary=torch.ones(1, 32, 32),
        cameras=cams,
        frame=torch.zeros(1, dtype=torch.long),
    )
    term = LOSSES.build("lpips")
    value = term(render, batch, {})
    value.backward()
    assert all_finite(value, rgb.grad)
    model64 = copy.deepcopy(term.__dict__["_model"]).double()
    ref = model64(rgb.detach().double().permute(0, 3, 1, 2), image.double().permute(0, 3, 1, 2), normalize=True)
    assert relative_error(value, ref.mean()) <= 1e-4

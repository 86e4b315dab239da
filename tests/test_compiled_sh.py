"""The compiled view colour (`framework.kernels.sh_colours`) against the torch path in float64, and the switch that
turns it on in an avatar's renders."""

from __future__ import annotations

import pytest
import torch

from framework.geometry import axis_angle_to_rotmat
from framework.kernels.sh_colours import view_colour_dc_compiled
from framework.splat.sh import view_colour_dc

F64 = torch.float64


def _inputs(n: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(n)
    coeffs = torch.randn(n, 16, 3, generator=g, dtype=F64)
    dirs = torch.randn(n, 3, generator=g, dtype=F64) * torch.rand(n, 1, generator=g, dtype=F64) * 4
    dirs[0] = 0.0  # the camera at the mean: only the constant term
    dirs[1] = torch.tensor([0.0, 1e-13, 0.0], dtype=F64)  # shorter than NORM_EPS: divided by the floor, not 1e-13
    frames = axis_angle_to_rotmat(torch.randn(n, 3, generator=g, dtype=F64) * 2)
    return coeffs.to(dtype), dirs.to(dtype), frames.to(dtype)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_matches_torch_in_float64(degree: int) -> None:
    """Every band against `view_colour_dc` (the torch basis, frames^T d by a batched product), all in float64."""
    coeffs, dirs, frames = _inputs(300, F64)
    got = view_colour_dc_compiled(degree, coeffs, dirs, frames)
    torch.testing.assert_close(got, view_colour_dc(degree, coeffs, dirs, frames), rtol=1e-12, atol=1e-12)
    assert got.shape == (300, 1, 3) and got.dtype == F64


def test_float32_agrees_to_rounding_and_keeps_the_dtype() -> None:
    coeffs, dirs, frames = _inputs(500, torch.float32)
    got = view_colour_dc_compiled(3, coeffs, dirs, frames)
    ref = view_colour_dc(3, coeffs.double(), dirs.double(), frames.double())
    assert got.dtype == torch.float32
    torch.testing.assert_close(got.double(), ref, rtol=1e-5, atol=1e-5)


def test_only_the_active_bands_are_read() -> None:
    """Coefficients beyond (degree + 1)^2 do not change the colour (a model whose schedule has not raised the degree
    yet keeps zeros there, but a compact export may hold anything)."""
    coeffs, dirs, frames = _inputs(50, F64)
    noisy = coeffs.clone()
    noisy[:, 4:] = 1e6
    torch.testing.assert_close(
        view_colour_dc_compiled(1, noisy, dirs, frames),
        view_colour_dc_compiled(1, coeffs, dirs, frames),
        rtol=0,
        atol=0,
    )


def test_a_bad_degree_is_refused() -> None:
    coeffs, dirs, frames = _inputs(5, F64)
    with pytest.raises(ValueError, match="sh_degree 3 needs"):
        view_colour_dc_compiled(3, coeffs[:, :9], dirs, frames)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_rasterizer_colours_match_torch_in_float64(degree: int) -> None:
    """The numba rasterizer's colours (`sh_colours_compiled`) against torch_ref's `sh_colors` for two cameras, one of
    them at a Gaussian's mean (only the constant term there), with colours below zero clamped in both."""
    from framework.kernels.sh_colours import sh_colours_compiled
    from plugins.rasterizer.torch_ref import sh_colors

    coeffs, dirs, _ = _inputs(300, F64)
    coeffs[:, 0] -= 2.0  # some colours fall below zero before the clamp
    means = dirs
    centres = torch.stack([torch.tensor([0.3, -0.2, 2.0], dtype=F64), means[5]])
    got = sh_colours_compiled(degree, coeffs, means, centres)
    ref = sh_colors(degree, coeffs, means[None] - centres[:, None])
    assert (ref == 0).any() and (ref > 0).any()
    torch.testing.assert_close(torch.from_numpy(got), ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_gradients_match_torch_in_float64(degree: int) -> None:
    """The training step's view colour: gradients to the coefficients (zero past the active bands), the directions
    and the frames against autograd through `view_colour_dc`, a zero direction and one below NORM_EPS included."""
    coeffs, dirs, frames = _inputs(200, F64)
    dirs[2] = torch.tensor([3e-12, -4e-12, 0.0], dtype=F64)  # just above the floor: the normalised branch
    ours = [t.clone().requires_grad_() for t in (coeffs, dirs, frames)]
    ref = [t.clone().requires_grad_() for t in (coeffs, dirs, frames)]
    out, expected = view_colour_dc_compiled(degree, *ours), view_colour_dc(degree, *ref)
    torch.testing.assert_close(out, expected, rtol=1e-12, atol=1e-12)
    proj = torch.randn(out.shape, generator=torch.Generator().manual_seed(degree), dtype=F64)
    (out * proj).sum().backward()
    (expected * proj).sum().backward()
    for name, a, b in zip(("coeffs", "dirs", "frames"), ours, ref, strict=True):
        if b.grad is None:  # degree 0: the colour does not depend on the direction
            assert degree == 0 and bool((a.grad == 0).all()), name
            continue
        scale = float(b.grad.abs().max())
        torch.testing.assert_close(a.grad, b.grad, rtol=1e-10, atol=1e-12 * max(scale, 1.0), msg=name)
    assert bool((ours[0].grad[:, (degree + 1) ** 2 :] == 0).all())


def test_gradcheck_through_every_band() -> None:
    coeffs, dirs, frames = _inputs(6, F64)
    dirs = dirs[2:]  # finite differences need a direction away from zero
    inputs = tuple(t[: dirs.shape[0]].clone().requires_grad_() for t in (coeffs, dirs, frames[2:]))
    assert torch.autograd.gradcheck(lambda c, d, r: view_colour_dc_compiled(3, c, d, r), inputs)

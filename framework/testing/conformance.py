"""The rasterizer conformance suite: what a backend must pass to be a `rasterizer` here.

Reusable by any backend, ours or a third party's. In a test file of your package write

    import pytest
    from framework.testing.conformance import *  # noqa: F401,F403

    @pytest.fixture(params=["my_backend"])
    def backend_name(request):
        return request.param

and run pytest on it. A backend that is not registered, or whose `requires` check fails here, is skipped with the
registry's reason. Override the `device` fixture to test on another device (default: CUDA when available).
A backend that computes in float32 whatever it is given (as gsplat's kernels do) says so with the class attribute
`supports_float64 = False`; the finite-difference test then uses float32 steps and tolerances (FD32_* below), and
every other check is the same. A backend that inverts its float32 screen covariance to get the conic (gsplat) says
`conic_from_float32_covariance = True`; the extreme scenes then allow the error that inversion makes for needle-thin
Gaussians (`extreme_tolerances`).
Every check compares against something independent of the backend: closed forms, finite differences, the float64
brute-force compositor in `framework.testing.reference`, or `torch_ref` (parity). The numerical-extremes properties
draw scenes with hypothesis (`framework.testing.properties` sets the number of examples: few by default, many with
SPLATRIG_HYPOTHESIS_PROFILE=slow).
"""

from __future__ import annotations

import math
import subprocess
import sys
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from torch import Tensor

from framework.interfaces.rasterizer import (
    ALPHA_MAX,
    ALPHA_MIN,
    FAR_PLANE,
    NEAR_PLANE,
    TRANSMITTANCE_MIN,
    Rasterizer,
)
from framework.plugins import load_plugins
from framework.registry import RASTERIZERS, UnknownComponentError
from framework.splat.sh import SH_C0, eval_sh, num_sh_bases
from framework.testing.properties import all_finite, relative_error, within_tolerance_except_jumps
from framework.types import Cameras, RenderOutput

__all__ = [
    "Scene",
    "make_camera",
    "make_random_scene",
    "render_scene",
    "build_backend",
    "device",
    "backend",
    "test_single_gaussian_footprint",
    "test_radii_closed_form",
    "test_radii_contain_footprint",
    "test_front_to_back_order",
    "test_alpha_and_depth",
    "test_culling",
    "test_sh_view_dependence",
    "test_empty_scene",
    "test_background",
    "test_single_pixel_image",
    "test_multi_camera_matches_single",
    "test_dtype_preserved",
    "test_means2d_grad",
    "test_gradients_finite_differences",
    "test_parity_with_torch_ref",
    "test_numerical_extremes",
    "extreme_scenes",
    "extreme_tolerances",
    "check_extreme_scene",
    "test_extremes_match_float64_reference",
    "test_transmittance_underflow_stack",
    "test_large_image_drawn_in_bands",
    "test_4096_image_in_bounded_memory",
    "test_half_precision_inputs_and_autocast",
]

PARITY_IMAGE_RTOL = 1e-4
PARITY_GRAD_RTOL = 1e-3

# Finite-difference gradient checks, chosen by the backend's `supports_float64`.
# float64: an absolute step of 1e-6; rounding (~1e-16 |L| / h) and truncation (~h^2 |f^(3)|) both stay far below
# 1e-5 of the largest finite difference plus 1e-7.
FD64_STEP = 1e-6
FD64_RTOL = 1e-5
FD64_ATOL = 1e-7
# float32: the loss carries rounding noise dL ~ k u ||w * out||_2 (u = 2^-24; each output is good to a few ulps,
# fast-math exp/log included, and independent errors add in quadrature; k = 64 leaves room for correlated ones), which
# a central difference turns into dL / h. Truncation is ~(h / l)^2 relative, l >= 0.02 being the smallest Gaussian
# scale of the scene. A step of 1e-3 times the tensor's largest magnitude keeps both small, and the check allows 1e-2
# of the largest finite difference plus dL / h. On torch_ref forced to float32 (tests/test_conformance_float32.py)
# the error is at most 2% of that over 20 random scenes; what it cannot absorb is a step that moves a pair across
# the 1/255 cut (a jump, ~100x the tolerance: 2 of those 20 scenes at this step), and the suite's fixed scene has
# none for steps from 5e-4 to 2e-3.
FD32_STEP = 1e-3
FD32_RTOL = 1e-2
FD32_NOISE_ULPS = 64


@dataclass
class Scene:
    """Activated Gaussian parameters plus cameras, ready for `Rasterizer.render`."""

    means: Tensor  # [N, 3]
    quats: Tensor  # [N, 4]
    scales: Tensor  # [N, 3]
    opacities: Tensor  # [N]
    sh: Tensor  # [N, K, 3]
    cameras: Cameras
    sh_degree: int

    def tensors(self) -> list[Tensor]:
        return [self.means, self.quats, self.scales, self.opacities, self.sh]

    def with_tensors(self, ts: list[Tensor]) -> Scene:
        return Scene(*ts, cameras=self.cameras, sh_degree=self.sh_degree)

    def to(self, device: str | torch.device) -> Scene:
        return Scene(*(t.to(device) for t in self.tensors()), self.cameras.to(device), self.sh_degree)


def make_camera(
    width: int,
    height: int,
    dist: float = 4.0,
    focal: float | None = None,
    yaw: float = 0.0,
    dtype: torch.dtype = torch.float32,
) -> Cameras:
    """One pinhole camera looking at the world origin from `dist` along -z, rotated by `yaw` about the y axis."""
    f = focal if focal is not None else 1.2 * max(width, height)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    c, s = math.cos(yaw), math.sin(yaw)
    R = torch.tensor([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]], dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[2, 3] = dist
    return Cameras(K[None].to(dtype), w2c[None].to(dtype), width, height)


def _stack_cameras(cams: list[Cameras]) -> Cameras:
    return Cameras(
        torch.cat([c.K for c in cams]), torch.cat([c.world_to_cam for c in cams]), cams[0].width, cams[0].height
    )


def make_random_scene(
    seed: int,
    n: int,
    width: int,
    height: int,
    dtype: torch.dtype = torch.float32,
    num_cameras: int = 1,
    sh_degree: int = 3,
    device: str | torch.device = "cpu",
    max_opacity: float = 0.95,
) -> Scene:
    """`n` random Gaussians of a few pixels inside the view of `num_cameras` cameras on an arc (deterministic)."""
    g = torch.Generator().manual_seed(seed)
    d = torch.float64
    means = (torch.rand(n, 3, generator=g, dtype=d) - 0.5) * torch.tensor([1.6, 1.6, 1.2], dtype=d)
    quats = torch.randn(n, 4, generator=g, dtype=d)
    scales = torch.exp(torch.empty(n, 3, dtype=d).uniform_(math.log(0.02), math.log(0.15), generator=g))
    opacities = 0.05 + (max_opacity - 0.05) * torch.rand(n, generator=g, dtype=d)
    sh = 0.3 * torch.randn(n, num_sh_bases(sh_degree), 3, generator=g, dtype=d)
    cams = _stack_cameras([make_camera(width, height, yaw=0.4 * i, dtype=d) for i in range(num_cameras)])
    scene = Scene(means, quats, scales, opacities, sh, cams, sh_degree)
    return Scene(*(t.to(device, dtype) for t in scene.tensors()), cams.to(device, dtype), sh_degree)


def single_gaussian(
    mean: tuple[float, float, float],
    scale: float | tuple[float, float, float],
    opacity: float,
    rgb: tuple[float, float, float] = (1.0, 1.0, 1.0),
    dtype: torch.dtype = torch.float64,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """One Gaussian of constant colour `rgb` (SH degree 0)."""
    s = (scale,) * 3 if isinstance(scale, float | int) else scale
    sh0 = (torch.tensor(rgb, dtype=torch.float64) - 0.5) / 0.28209479177387814
    return (
        torch.tensor([mean], dtype=dtype),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype),
        torch.tensor([s], dtype=dtype),
        torch.tensor([opacity], dtype=dtype),
        sh0.reshape(1, 1, 3).to(dtype),
    )


def render_scene(backend: Rasterizer, scene: Scene, **kwargs) -> RenderOutput:
    return backend.render(*scene.tensors(), scene.cameras, sh_degree=scene.sh_degree, **kwargs)


def build_backend(name: str) -> Rasterizer:
    """Build `name` from the registry, or skip the calling test with the registry's reason."""
    load_plugins()
    try:
        entry = RASTERIZERS.entry(name)
    except UnknownComponentError as exc:
        pytest.skip(f"rasterizer '{name}' is not registered here: {str(exc).splitlines()[0]}")
    reason = entry.unavailable_reason()
    if reason is not None:
        pytest.skip(f"rasterizer '{name}' is unavailable: {reason}")
    return RASTERIZERS.build(name)


@pytest.fixture
def device() -> str:
    from framework.runtime import default_device

    return default_device()


@pytest.fixture
def backend(backend_name: str) -> Rasterizer:
    return build_backend(backend_name)


def _on(scene: Scene, device: str) -> Scene:
    return scene.to(device)


def _cpu64(x: Tensor) -> Tensor:
    return x.detach().to("cpu", torch.float64)


# ---------------------------------------------------------------- closed forms


def test_single_gaussian_footprint(backend: Rasterizer, device: str) -> None:
    """An isotropic Gaussian on the optical axis: alpha(p) = o exp(-|d|^2 / (2 s2)), s2 = (f s / z)^2 + 0.3."""
    W = H = 32
    f, z, s, o = 40.0, 4.0, 0.25, 0.6
    cams = make_camera(W, H, dist=z, focal=f, dtype=torch.float64)
    g = single_gaussian((0.0, 0.0, 0.0), s, o, rgb=(0.2, 0.5, 0.9))
    out = backend.render(*(t.to(device) for t in g), cams.to(device), sh_degree=0)
    s2 = (f * s / z) ** 2 + 0.3
    jj, ii = torch.meshgrid(torch.arange(W, dtype=torch.float64), torch.arange(H, dtype=torch.float64), indexing="xy")
    d2 = (jj + 0.5 - W / 2) ** 2 + (ii + 0.5 - H / 2) ** 2
    expected = o * torch.exp(-0.5 * d2 / s2)
    expected = torch.where(expected >= ALPHA_MIN, expected, torch.zeros_like(expected))
    alpha = _cpu64(out.alpha[0, ..., 0])
    torch.testing.assert_close(alpha, expected, atol=1e-5, rtol=0)
    # peak at the four centre pixels and the integral ~ o * 2 pi s2 (the 1/255 cut removes a little)
    assert abs(float(alpha.max()) - o * math.exp(-0.5 * 0.5 / s2)) < 1e-5
    integral = float(alpha.sum())
    assert integral == pytest.approx(o * 2 * math.pi * s2, rel=0.03)
    rgb = _cpu64(out.rgb[0])
    torch.testing.assert_close(
        rgb, alpha[..., None] * torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64), atol=1e-5, rtol=0
    )


def test_radii_closed_form(backend: Rasterizer, device: str) -> None:
    """radius = ceil(min(3.33, sqrt(2 ln(255 o))) * sqrt(Sigma2d)) for an isotropic Gaussian on the axis."""
    W = H = 64
    f, z, s = 50.0, 4.0, 0.3
    cams = make_camera(W, H, dist=z, focal=f, dtype=torch.float64)
    for o in (0.02, 0.3, 0.999):
        g = single_gaussian((0.0, 0.0, 0.0), s, o)
        out = backend.render(*(t.to(device) for t in g), cams.to(device), sh_degree=0)
        extend = min(3.33, math.sqrt(2 * math.log(255 * o)))
        expected = math.ceil(extend * math.sqrt((f * s / z) ** 2 + 0.3))
        assert int(out.radii[0, 0]) == expected, (o, int(out.radii[0, 0]), expected)
    g = single_gaussian((0.0, 0.0, 0.0), s, 0.5 / 255)  # can never reach alpha 1/255
    out = backend.render(*(t.to(device) for t in g), cams.to(device), sh_degree=0)
    assert int(out.radii[0, 0]) == 0
    assert float(out.alpha.abs().max()) == 0.0


def test_radii_contain_footprint(backend: Rasterizer, device: str) -> None:
    """Every pixel a Gaussian reaches (alpha > 0) lies within `radius` of its projected centre."""
    scene = make_random_scene(3, 12, 40, 36, dtype=torch.float64, sh_degree=0)
    for i in range(scene.means.shape[0]):
        one = scene.with_tensors([t[i : i + 1] for t in scene.tensors()])
        out = render_scene(backend, _on(one, device))
        alpha = _cpu64(out.alpha[0, ..., 0])
        r = int(out.radii[0, 0])
        if r == 0:
            assert float(alpha.max()) == 0.0
            continue
        ii, jj = torch.nonzero(alpha > 0, as_tuple=True)
        m = _cpu64(out.means2d[0, 0])
        assert float((jj + 0.5 - m[0]).abs().max()) <= r + 1e-6
        assert float((ii + 0.5 - m[1]).abs().max()) <= r + 1e-6


def test_front_to_back_order(backend: Rasterizer, device: str) -> None:
    """Two overlapping Gaussians: the nearer one is composited first whatever their order in the arrays."""
    W = H = 16
    cams = make_camera(W, H, dist=4.0, focal=20.0, dtype=torch.float64)
    near_g = single_gaussian((0.0, 0.0, -1.0), 0.6, 0.7, rgb=(1.0, 0.0, 0.0))
    far_g = single_gaussian((0.0, 0.0, 1.0), 0.6, 0.8, rgb=(0.0, 0.0, 1.0))
    outs = []
    for a, b in ((near_g, far_g), (far_g, near_g)):
        ts = [torch.cat([x, y]).to(device) for x, y in zip(a, b, strict=True)]
        outs.append(backend.render(*ts, cams.to(device), sh_degree=0))
    torch.testing.assert_close(_cpu64(outs[0].rgb), _cpu64(outs[1].rgb), atol=1e-6, rtol=0)

    # at a centre pixel: alpha_i = o_i exp(-sigma_i) with d = (0.5, 0.5) px from the centre (8, 8)
    def a_at(o: float, z: float) -> float:
        s2 = (20.0 * 0.6 / z) ** 2 + 0.3
        return o * math.exp(-0.5 * 0.5 / s2)

    a1, a2 = a_at(0.7, 3.0), a_at(0.8, 5.0)
    rgb = _cpu64(outs[0].rgb[0, 8, 8])
    assert float(rgb[0]) == pytest.approx(a1, abs=1e-5)
    assert float(rgb[2]) == pytest.approx((1 - a1) * a2, abs=1e-5)
    assert float(outs[0].alpha[0, 8, 8, 0]) == pytest.approx(1 - (1 - a1) * (1 - a2), abs=1e-5)
    assert float(outs[0].depth[0, 8, 8, 0]) == pytest.approx(a1 * 3.0 + (1 - a1) * a2 * 5.0, abs=1e-4)


def test_alpha_and_depth(backend: Rasterizer, device: str) -> None:
    """One Gaussian: depth = alpha * z and alpha = 1 - T; a stack of opaque layers stops at T <= 1e-4."""
    W = H = 12
    cams = make_camera(W, H, dist=4.0, focal=15.0, dtype=torch.float64)
    g = single_gaussian((0.1, -0.1, 0.5), 0.5, 0.9)
    out = backend.render(*(t.to(device) for t in g), cams.to(device), sh_degree=0)
    torch.testing.assert_close(_cpu64(out.depth), _cpu64(out.alpha) * 4.5, atol=1e-6, rtol=0)
    # 5 layers of alpha 0.95 (centred on a pixel centre): T after k layers = 0.05^k; the 4th would take T to
    # 6.25e-6 <= 1e-4, so it is not added and the pixel is finished: T_final = 1.25e-4, layers 1..3 only appear.
    layers = [single_gaussian((0.0, 0.0, -1.0 + 0.5 * k), 0.5, 0.95, rgb=(0.1 * (k + 1),) * 3) for k in range(5)]
    ts = [torch.cat(parts).to(device) for parts in zip(*layers, strict=True)]
    K = cams.K.clone()
    K[0, 0, 2] = K[0, 1, 2] = 6.5  # the mean projects onto the centre of pixel (6, 6)
    out = backend.render(*ts, Cameras(K, cams.world_to_cam, W, H).to(device), sh_degree=0)
    weights = [0.95, 0.05 * 0.95, 0.05**2 * 0.95]
    assert float(out.alpha[0, 6, 6, 0]) == pytest.approx(1 - 0.05**3, abs=1e-6)
    assert float(out.rgb[0, 6, 6, 0]) == pytest.approx(sum(w * 0.1 * (k + 1) for k, w in enumerate(weights)), abs=1e-6)
    assert float(out.depth[0, 6, 6, 0]) == pytest.approx(
        sum(w * (3.0 + 0.5 * k) for k, w in enumerate(weights)), abs=1e-5
    )


def test_culling(backend: Rasterizer, device: str) -> None:
    """Behind the camera, at the near plane, beyond the far plane, outside the image: radius 0, nothing drawn."""
    W, H = 20, 16
    cams = make_camera(W, H, dist=4.0, focal=20.0, dtype=torch.float64).to(device)
    cases = {
        "behind": (0.0, 0.0, -5.0),
        "at_near": (0.0, 0.0, -4.0 + NEAR_PLANE),
        "outside_right": (6.0, 0.0, 0.0),
        "outside_top": (0.0, -6.0, 0.0),
    }
    for name, mean in cases.items():
        g = single_gaussian(mean, 0.3, 0.9)
        out = backend.render(*(t.to(device) for t in g), cams, sh_degree=0)
        assert int(out.radii[0, 0]) == 0, name
        assert float(out.alpha.abs().max()) == 0.0, name
    g = single_gaussian((0.0, 0.0, 0.0), 0.3, 0.9)
    out = backend.render(*(t.to(device) for t in g), cams, sh_degree=0, far=3.0)
    assert int(out.radii[0, 0]) == 0 and float(out.alpha.max()) == 0.0, "beyond far"
    out = backend.render(*(t.to(device) for t in g), cams, sh_degree=0, near=4.5)
    assert int(out.radii[0, 0]) == 0 and float(out.alpha.max()) == 0.0, "custom near"
    out = backend.render(*(t.to(device) for t in g), cams, sh_degree=0)
    assert int(out.radii[0, 0]) > 0 and float(out.alpha.max()) > 0.5, "visible control"


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_sh_view_dependence(backend: Rasterizer, device: str, degree: int) -> None:
    """The colour at the Gaussian's own pixel is alpha * max(eval_sh(dir) + 0.5, 0) for cameras around it."""
    W = H = 9
    o = 0.8
    g = torch.Generator().manual_seed(degree)
    sh = 0.4 * torch.randn(1, num_sh_bases(degree), 3, generator=g, dtype=torch.float64)
    mean = torch.tensor([[0.05, -0.03, 0.02]], dtype=torch.float64)
    colours = []
    for yaw in (0.0, 0.7, -1.1, 2.5):
        cams = make_camera(W, H, dist=3.0, focal=10.0, yaw=yaw, dtype=torch.float64)
        # put the principal point so that the mean projects exactly onto the centre of pixel (4, 4)
        pc = cams.world_to_cam[0, :3, :3] @ mean[0] + cams.world_to_cam[0, :3, 3]
        K = cams.K.clone()
        K[0, 0, 2] = 4.5 - 10.0 * pc[0] / pc[2]
        K[0, 1, 2] = 4.5 - 10.0 * pc[1] / pc[2]
        cams = Cameras(K, cams.world_to_cam, W, H)
        ts = [mean, torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.05), torch.tensor([o]), sh]
        out = backend.render(*(t.to(device, torch.float64) for t in ts), cams.to(device), sh_degree=degree)
        expected = o * (eval_sh(degree, sh[0], mean[0] - cams.centers()[0]) + 0.5).clamp_min(0)
        got = _cpu64(out.rgb[0, 4, 4])
        torch.testing.assert_close(got, expected, atol=1e-5, rtol=0)
        colours.append(got)
    assert float((colours[0] - colours[2]).abs().max()) > 1e-3  # it does depend on the view


def test_empty_scene(backend: Rasterizer, device: str) -> None:
    W, H = 10, 7
    cams = make_camera(W, H).to(device)
    bg = torch.tensor([0.2, 0.4, 0.6], device=device)
    z = torch.zeros(0, 3, device=device, requires_grad=True)
    out = backend.render(
        z,
        torch.zeros(0, 4, device=device),
        torch.zeros(0, 3, device=device),
        torch.zeros(0, device=device),
        torch.zeros(0, 1, 3, device=device),
        cams,
        sh_degree=0,
        background=bg,
    )
    assert out.rgb.shape == (1, H, W, 3) and out.alpha.shape == (1, H, W, 1)
    assert out.means2d.shape == (1, 0, 2) and out.radii.shape == (1, 0)
    torch.testing.assert_close(out.rgb, bg.expand(1, H, W, 3))
    assert float(out.alpha.detach().abs().max()) == 0.0
    if out.depth is not None:
        assert float(out.depth.detach().abs().max()) == 0.0


def test_background(backend: Rasterizer, device: str) -> None:
    """rgb(bg) - rgb(black) = (1 - alpha) * bg."""
    scene = _on(make_random_scene(1, 30, 24, 20), device)
    bg = torch.tensor([0.3, 0.9, 0.1], device=device)
    black = render_scene(backend, scene)
    coloured = render_scene(backend, scene, background=bg)
    torch.testing.assert_close(coloured.rgb - black.rgb, (1 - black.alpha) * bg, atol=1e-6, rtol=0)
    torch.testing.assert_close(coloured.alpha, black.alpha)


def test_single_pixel_image(backend: Rasterizer, device: str) -> None:
    scene = make_random_scene(2, 20, 1, 1, dtype=torch.float64)
    out = render_scene(backend, _on(scene, device))
    from framework.testing.reference import reference_render

    ref = reference_render(*scene.tensors(), scene.cameras.K, scene.cameras.world_to_cam, 1, 1, scene.sh_degree)
    torch.testing.assert_close(_cpu64(out.rgb), ref["rgb"], atol=1e-6, rtol=0)
    torch.testing.assert_close(_cpu64(out.alpha), ref["alpha"], atol=1e-6, rtol=0)


def test_multi_camera_matches_single(backend: Rasterizer, device: str) -> None:
    scene = _on(make_random_scene(4, 40, 20, 16, num_cameras=3), device)
    both = render_scene(backend, scene)
    for c in range(3):
        one = render_scene(backend, Scene(*scene.tensors(), scene.cameras.index(c), scene.sh_degree))
        torch.testing.assert_close(both.rgb[c : c + 1], one.rgb, atol=1e-6, rtol=0)
        torch.testing.assert_close(both.radii[c : c + 1], one.radii)


def test_dtype_preserved(backend: Rasterizer, device: str) -> None:
    out = render_scene(backend, _on(make_random_scene(5, 10, 8, 8), device))
    assert out.rgb.dtype == torch.float32 and out.alpha.dtype == torch.float32
    assert out.rgb.shape == (1, 8, 8, 3) and out.means2d.shape == (1, 10, 2) and out.radii.shape == (1, 10)


# ---------------------------------------------------------------- gradients


def test_means2d_grad(backend: Rasterizer, device: str) -> None:
    """means2d.grad is filled by backward: finite, non-zero for drawn Gaussians, zero for culled ones."""
    scene = make_random_scene(6, 20, 24, 20)
    means = scene.means.clone()
    means[0] = torch.tensor([0.0, 0.0, -10.0])  # behind the camera
    scene = _on(scene.with_tensors([means, *scene.tensors()[1:]]), device)
    params = [t.clone().requires_grad_() for t in scene.tensors()]
    out = render_scene(backend, scene.with_tensors(params))
    (out.rgb.sum() + out.alpha.sum()).backward()
    g = out.means2d.grad
    assert g is not None and g.shape == (1, 20, 2)
    assert torch.isfinite(g).all()
    assert float(g[0, 0].abs().max()) == 0.0
    drawn = out.radii[0] > 0
    assert float(g[0, drawn].abs().sum(-1).gt(0).float().mean()) > 0.5


def _loss_weights(out: RenderOutput, seed: int) -> list[Tensor]:
    g = torch.Generator().manual_seed(seed)
    ws = [
        torch.randn(out.rgb.shape, generator=g, dtype=torch.float64),
        torch.randn(out.alpha.shape, generator=g, dtype=torch.float64),
    ]
    if out.depth is not None:
        ws.append(torch.randn(out.depth.shape, generator=g, dtype=torch.float64))
    return ws


def _loss_terms(out: RenderOutput, ws: list[Tensor]) -> Tensor:
    """Every w * output, flattened, in float64 (so summing them adds no rounding of its own)."""
    parts = [out.rgb, out.alpha] + ([out.depth] if out.depth is not None else [])
    return torch.cat([(p.double() * w.to(p.device)).reshape(-1) for p, w in zip(parts, ws, strict=True)])


def _weighted_loss(out: RenderOutput, ws: list[Tensor]) -> Tensor:
    return _loss_terms(out, ws).sum()


def test_gradients_finite_differences(backend: Rasterizer, device: str) -> None:
    """Analytic gradients of a random linear functional of (rgb, alpha, depth) vs central differences: in float64, or
    with float32 steps and tolerances (FD32_* above) for a backend that computes in float32 (`supports_float64`)."""
    f64 = backend.supports_float64
    dtype = torch.float64 if f64 else torch.float32
    scene = _on(make_random_scene(7, 3, 12, 10, dtype=dtype, sh_degree=2, max_opacity=0.7), device)
    params = [t.clone().requires_grad_() for t in scene.tensors()]
    out = render_scene(backend, scene.with_tensors(params))
    ws = _loss_weights(out, 0)
    grads = torch.autograd.grad(_weighted_loss(out, ws), params)
    loss_noise = FD32_NOISE_ULPS * 2.0**-24 * float(_loss_terms(out, ws).detach().norm())  # dL, used in float32
    for k, (p, gk) in enumerate(zip(scene.tensors(), grads, strict=True)):
        h = FD64_STEP if f64 else FD32_STEP * float(p.abs().max())
        fd = torch.zeros(p.numel(), dtype=torch.float64)
        for i in range(p.numel()):
            vals, at = [], []
            for sgn in (1, -1):
                q = p.clone()
                q.view(-1)[i] += sgn * h
                at.append(float(q.view(-1)[i]))  # the perturbed value as the dtype holds it
                ts = list(scene.tensors())
                ts[k] = q
                with torch.no_grad():
                    vals.append(float(_weighted_loss(render_scene(backend, scene.with_tensors(ts)), ws)))
            fd[i] = (vals[0] - vals[1]) / (at[0] - at[1])
        err = float((_cpu64(gk).reshape(-1) - fd).abs().max())
        scale = max(float(fd.abs().max()), 1e-3)
        tol = FD64_RTOL * scale + FD64_ATOL if f64 else FD32_RTOL * scale + loss_noise / h
        assert err <= tol, f"parameter {k}: max |analytic - FD| = {err:.3g} > {tol:.3g} (scale {scale:.3g})"


def _rel(a: Tensor, b: Tensor) -> float:
    a, b = _cpu64(a), _cpu64(b)
    return float((a - b).norm() / b.norm().clamp_min(1e-12))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_parity_with_torch_ref(backend: Rasterizer, backend_name: str, device: str, seed: int) -> None:
    """Random float32 scenes: image within 1e-4 and gradients within 1e-3 (relative L2) of torch_ref.

    torch_ref itself is held to the float64 brute-force compositor instead (and to float32 vs float64 self-parity).
    """
    scene = _on(make_random_scene(seed, 60, 40, 32, num_cameras=2), device)
    bg = torch.tensor([0.1, 0.2, 0.3], device=device)
    if backend_name == "torch_ref":
        from framework.testing.reference import reference_render

        s64 = make_random_scene(seed, 60, 40, 32, dtype=torch.float64, num_cameras=2)
        ref = reference_render(*s64.tensors(), s64.cameras.K, s64.cameras.world_to_cam, 40, 32, 3, background=bg.cpu())
        got = render_scene(backend, s64.to(device), background=bg.double())
        for key in ("rgb", "alpha", "depth"):
            assert _rel(getattr(got, key), ref[key]) < 1e-10, key
        other = build_backend("torch_ref")
        ref_dev = device
        ref_scene = _on(s64, device)
    else:
        other, ref_dev, ref_scene = build_backend("torch_ref"), device, scene

    def run(b: Rasterizer, sc: Scene) -> tuple[RenderOutput, list[Tensor]]:
        params = [t.clone().requires_grad_() for t in sc.tensors()]
        out = render_scene(b, sc.with_tensors(params), background=bg.to(sc.means.dtype))
        _weighted_loss(out, _loss_weights(out, seed)).backward()
        return out, [p.grad for p in params] + [out.means2d.grad]

    out_b, g_b = run(backend, scene)
    out_r, g_r = run(other, ref_scene.to(ref_dev))
    for key in ("rgb", "alpha"):
        assert _rel(getattr(out_b, key), getattr(out_r, key)) <= PARITY_IMAGE_RTOL, key
    if out_b.depth is not None:
        assert _rel(out_b.depth, out_r.depth) <= PARITY_IMAGE_RTOL, "depth"
    names = ["means", "quats", "scales", "opacities", "sh", "means2d"]
    for name, a, b in zip(names, g_b, g_r, strict=True):
        assert a is not None, f"no gradient for {name}"
        assert _rel(a, b) <= PARITY_GRAD_RTOL, f"{name}: relative gradient error {_rel(a, b):.3g}"
    diff = (out_b.radii.cpu().long() - out_r.radii.cpu().long()).abs()
    assert int(diff.max()) <= 1 and float((diff == 0).float().mean()) >= 0.98, "radii"


def test_numerical_extremes(backend: Rasterizer, device: str) -> None:
    """Tiny/huge scales, (near-)zero quaternions, opacity 0 and 1 - 1e-7, Gaussians at the near plane: finite values
    and finite gradients everywhere."""
    base = make_random_scene(8, 12, 16, 12)
    means, quats, scales, opac, sh = (t.clone() for t in base.tensors())
    scales[0] = 1e-6
    scales[1] = torch.tensor([1e3, 1e-6, 1e2])
    quats[2] = 0.0
    quats[3] = 1e-30
    opac[4] = 0.0
    opac[5] = 1 - 1e-7
    opac[6] = 1 - 1e-7
    means[6] = torch.tensor([0.0, 0.0, 0.0])
    means[7] = torch.tensor([0.0, 0.0, -4.0 + NEAR_PLANE * 1.0001])  # just in front of the near plane
    means[8] = torch.tensor([0.01, 0.0, -4.0 + NEAR_PLANE])  # exactly at it
    means[9] = torch.tensor([0.0, 0.0, -4.0])  # at the camera centre
    scene = _on(Scene(means, quats, scales, opac, sh, base.cameras, base.sh_degree), device)
    params = [t.clone().requires_grad_() for t in scene.tensors()]
    out = render_scene(backend, scene.with_tensors(params), background=torch.ones(3, device=device))
    for name in ("rgb", "alpha", "depth", "means2d"):
        val = getattr(out, name)
        if val is not None:
            assert torch.isfinite(val).all(), name
    assert float(out.alpha.detach().min()) >= 0.0 and float(out.alpha.detach().max()) <= 1.0
    (out.rgb.sum() + out.alpha.sum() + (out.depth.sum() if out.depth is not None else 0)).backward()
    for name, p in zip(["means", "quats", "scales", "opacities", "sh"], params, strict=True):
        assert p.grad is not None and torch.isfinite(p.grad).all(), name


# ---------------------------------------------------------------- numerical extremes (hypothesis)

EXTREME_W, EXTREME_H, EXTREME_F = 16, 12, 20.0
EXTREME_VALUE_TOL = 2e-4  # float32 vs the float64 reference, per pixel (rgb, alpha; depth relative to its scale)
EXTREME_JUMP = 5 * ALPHA_MIN  # a pair within rounding of the 1/255 cut: one colour (<= 5) times 1/255
EXTREME_GRAD_RTOL = 2e-3  # relative L2 error of each float32 gradient vs float64 (compared when no pixel jumped)
POSITIONS = (
    "inside",
    "behind",
    "camera_centre",
    "at_near",
    "just_inside_near",
    "beyond_far",
    "far_outside",
    "covering",
)
QUAT_NORMS = (0.0, 1e-30, 1e-20, 1e-8, 1e-3, 1.0, 1e3)
# A conic formed as 1 / (a c - b^2) of a float32 screen covariance with condition number kappa carries a relative
# error of about 2 kappa u (u = eps32 / 2, the determinant's cancellation). The opacity o exp(-sigma) then moves by at
# most o sigma exp(-sigma) 2 kappa u <= 0.37 kappa eps32 (sigma exp(-sigma) <= 1/e); gradients, which hold the conic
# squared, by a few times that. Measured per kappa * eps32: gsplat 1.5.3 on an H200, 0.16 (alpha) and 0.9 (the means'
# gradient, relative) at kappa 2e4; its CPU emulation over 36 needles (tests/test_conic_precision.py), up to 0.15
# and 4.6. The factors below hold both with a margin and apply only to `conic_from_float32_covariance` backends.
CONIC_VALUE_PER_KAPPA_EPS = 0.5
CONIC_GRAD_PER_KAPPA_EPS = 8.0


def _f32_above(x: float) -> float:
    """The smallest float32 above x, as a float64 value (exactly representable in both precisions)."""
    return float(np.nextafter(np.float32(x), np.float32(np.inf)))


def extreme_camera(dtype: torch.dtype = torch.float64) -> Cameras:
    """An identity-pose camera (camera space = world space, so a Gaussian's z is exactly its depth), 16 x 12 px."""
    K = torch.tensor([[EXTREME_F, 0.0, EXTREME_W / 2], [0.0, EXTREME_F, EXTREME_H / 2], [0.0, 0.0, 1.0]], dtype=dtype)
    return Cameras(K[None], torch.eye(4, dtype=dtype)[None], EXTREME_W, EXTREME_H)


@st.composite
def extreme_scenes(draw: st.DrawFn, max_gaussians: int = 6) -> Scene:
    """float64 scenes of 1..max_gaussians Gaussians, each drawn from the extremes of issue 11: scales 1e-7..1e3 m
    (scene size ~1 m) with anisotropy up to 1e6; quaternions of norm 0, 1e-30 .. 1e3 (non-normalised); opacity logits
    of +-30 or moderate; positions inside the view, behind the camera, at its centre, exactly at and just inside the
    near plane, beyond the far plane, far outside the image, or close and large enough to cover the whole image."""
    n = draw(st.integers(1, max_gaussians))
    degree = draw(st.integers(0, 3))
    rows = []
    for _ in range(n):
        where = draw(st.sampled_from(POSITIONS))
        u, v = draw(st.floats(-1.0, 1.0)), draw(st.floats(-1.0, 1.0))
        log_s = np.array([draw(st.floats(math.log(1e-7), math.log(1e3))) for _ in range(3)])
        if where == "covering":
            log_s = np.maximum(log_s, 0.0)  # >= 1 m at 1-3 m from the camera: larger than the whole view
        log_s = np.maximum(log_s, log_s.max() - math.log(1e6))  # anisotropy <= 1e6
        z = draw(st.floats(0.5, 8.0))
        mean = {
            "inside": (0.4 * u * z, 0.3 * v * z, z),
            "behind": (u, v, -z),
            "camera_centre": (0.0, 0.0, 0.0),
            "at_near": (1e-3 * u, 1e-3 * v, NEAR_PLANE),
            "just_inside_near": (1e-3 * u, 1e-3 * v, _f32_above(NEAR_PLANE)),
            "beyond_far": (u, v, 2 * FAR_PLANE),
            "far_outside": (1e6 * math.copysign(1.0, u), v, z),
            "covering": (0.1 * u, 0.1 * v, 1.0 + abs(v)),
        }[where]
        direction = np.array([draw(st.floats(-1.0, 1.0)) for _ in range(4)])
        if np.linalg.norm(direction) < 1e-3:
            direction = np.array([1.0, 0.0, 0.0, 0.0])
        quat = direction / np.linalg.norm(direction) * draw(st.sampled_from(QUAT_NORMS))
        logit = draw(st.one_of(st.sampled_from([-30.0, 30.0]), st.floats(-6.0, 6.0)))
        rows.append((mean, quat, np.exp(log_s), 1.0 / (1.0 + math.exp(-logit))))
    seed = draw(st.integers(0, 2**31 - 1))
    f64 = torch.float64
    sh = 0.5 * torch.randn(n, num_sh_bases(degree), 3, generator=torch.Generator().manual_seed(seed), dtype=f64)
    return Scene(
        torch.tensor([r[0] for r in rows], dtype=f64),
        torch.tensor(np.stack([r[1] for r in rows]), dtype=f64),
        torch.tensor(np.stack([r[2] for r in rows]), dtype=f64),
        torch.tensor([r[3] for r in rows], dtype=f64),
        sh,
        extreme_camera(),
        degree,
    )


def screen_condition_number(scene: Scene) -> float:
    """The largest condition number (largest over smallest eigenvalue) of a drawn Gaussian's dilated screen covariance
    in the first camera, in float64: what a float32 conic computed as 1 / (a c - b^2) loses digits to (reported when
    an extreme scene fails, so a backend's error can be read against it)."""
    from framework.testing.reference import _project_one

    c = scene.cameras
    worst = 1.0
    with torch.no_grad():
        for g in range(scene.means.shape[0]):
            z, _, cov = _project_one(
                scene.means[g], scene.quats[g], scene.scales[g], c.K[0], c.world_to_cam[0], c.width, c.height
            )
            eig = torch.linalg.eigvalsh(cov)
            if NEAR_PLANE < float(z) < FAR_PLANE and float(eig[0]) > 0:
                worst = max(worst, float(eig[1] / eig[0]))
    return worst


def _extreme_loss(rgb: Tensor, alpha: Tensor, depth: Tensor | None) -> Tensor:
    """A fixed random linear functional of the outputs (depth scaled to the colours' range)."""
    g = torch.Generator().manual_seed(11)
    w = [torch.randn(t.shape, generator=g, dtype=torch.float64).to(t.device, t.dtype) for t in (rgb, alpha)]
    loss = (rgb * w[0]).sum() + (alpha * w[1]).sum()
    if depth is not None:
        loss = loss + 1e-2 * (depth * torch.randn(depth.shape, generator=g, dtype=torch.float64).to(depth)).sum()
    return loss


def extreme_tolerances(backend: Rasterizer, scene: Scene) -> tuple[float, float]:
    """(per-pixel value tolerance, relative gradient tolerance) of `check_extreme_scene` for this backend and scene:
    EXTREME_VALUE_TOL and EXTREME_GRAD_RTOL, plus the conic's kappa * eps32 terms for a backend that inverts its float32
    screen covariance (`conic_from_float32_covariance`). Past kappa * eps32 ~ 0.1 such a conic has no digits left,
    and only finiteness and 0 <= alpha <= 1 still bind."""
    if not backend.conic_from_float32_covariance:
        return EXTREME_VALUE_TOL, EXTREME_GRAD_RTOL
    kappa_eps = screen_condition_number(scene) * torch.finfo(torch.float32).eps
    return (
        EXTREME_VALUE_TOL + CONIC_VALUE_PER_KAPPA_EPS * kappa_eps,
        EXTREME_GRAD_RTOL + CONIC_GRAD_PER_KAPPA_EPS * kappa_eps,
    )


def check_extreme_scene(backend: Rasterizer, device: str, scene: Scene) -> None:
    """A float32 render of `scene` against the float64 brute-force reference: finite values and gradients, values
    within `extreme_tolerances` (except a pixel or two that jump by <= 5/255 at the 1/255 cut, see
    `within_tolerance_except_jumps`), and, where no pixel jumped, gradients within its relative tolerance."""
    from framework.testing.reference import reference_render

    value_tol, grad_rtol = extreme_tolerances(backend, scene)
    ref_params = [t.clone().requires_grad_() for t in scene.tensors()]
    c = scene.cameras
    ref = reference_render(*ref_params, c.K, c.world_to_cam, c.width, c.height, scene.sh_degree)
    ref_loss = _extreme_loss(ref["rgb"], ref["alpha"], ref["depth"])
    no_grad: list[Tensor | None] = [None] * len(ref_params)  # nothing drawn: the reference has no graph at all
    ref_grads = torch.autograd.grad(ref_loss, ref_params, allow_unused=True) if ref_loss.requires_grad else no_grad
    params = [t.to(device, torch.float32).requires_grad_() for t in scene.tensors()]
    out = backend.render(*params, c.to(device, torch.float32), sh_degree=scene.sh_degree)
    grads = torch.autograd.grad(_extreme_loss(out.rgb, out.alpha, out.depth), params, allow_unused=True)
    assert all_finite(out.rgb, out.alpha, out.depth, out.means2d, *grads), "non-finite output or gradient"
    assert float(out.alpha.detach().min()) >= 0.0 and float(out.alpha.detach().max()) <= 1.0
    exact = True
    for key in ("rgb", "alpha", "depth"):
        got = getattr(out, key)
        if got is None:
            continue
        got, want = got.detach(), ref[key].detach()
        scale = max(1.0, float(want.abs().max())) if key == "depth" else 1.0
        err = float((got.cpu().double() - want).abs().max())
        assert within_tolerance_except_jumps(got, want, value_tol * scale, EXTREME_JUMP * scale), (
            f"{key}: max error {err:.3g} (tolerance {value_tol * scale:.3g}, jumps to "
            f"{EXTREME_JUMP * scale:.3g}); screen covariance condition number up to "
            f"{screen_condition_number(scene):.3g}"
        )
        exact &= err <= value_tol * scale
    if exact:
        names = ("means", "quats", "scales", "opacities", "sh")
        zero = [torch.zeros_like(t) for t in scene.tensors()]
        ref_grads = [z if r is None else r for z, r in zip(zero, ref_grads, strict=True)]
        for name, g, r in zip(names, grads, ref_grads, strict=True):
            if g is None:
                continue
            atol = 0.0
            if name == "quats":
                # Turning an isotropic Gaussian changes nothing: the exact gradient cancels to ~0, and float32 keeps a
                # rounding residue on the scale of the gradient an anisotropic Gaussian would get, |dL/ds| s / |q|.
                q_norm = scene.quats.norm(dim=-1).clamp_min(1e-30)
                atol = float(((ref_grads[2] * scene.scales).abs().sum(-1) / q_norm).norm())
            err = float((g.detach().double().cpu() - r).norm())
            assert err <= grad_rtol * (float(r.norm()) + atol), (
                f"{name}: {err:.3g} vs |ref| {r.norm():.3g} (relative tolerance {grad_rtol:.3g}); screen "
                f"covariance condition number up to {screen_condition_number(scene):.3g}"
            )


@given(scene=extreme_scenes())
def test_extremes_match_float64_reference(backend: Rasterizer, device: str, scene: Scene) -> None:
    """float32 renders of extreme scenes against the float64 brute-force reference (`check_extreme_scene`)."""
    check_extreme_scene(backend, device, scene)


STACK_COUNT = 2000


def _stack_scene(opacity: float) -> Scene:
    """2000 Gaussians in depth order on the optical axis of a 1 x 1 camera: each projects exactly onto the pixel
    centre (sigma = 0, alpha = min(opacity, 0.999)), and each is one pair of that pixel whatever its opacity (one
    compiled shape for a JIT backend)."""
    f64 = torch.float64
    z = torch.linspace(2.0, 6.0, STACK_COUNT, dtype=f64)
    return Scene(
        torch.stack([torch.zeros_like(z), torch.zeros_like(z), z], dim=-1),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=f64).expand(STACK_COUNT, 4).contiguous(),
        torch.full((STACK_COUNT, 3), 0.02, dtype=f64),
        torch.full((STACK_COUNT,), opacity, dtype=f64),
        0.5 * torch.randn(STACK_COUNT, 1, 3, generator=torch.Generator().manual_seed(0), dtype=f64),
        Cameras(
            torch.tensor([[[EXTREME_F, 0.0, 0.5], [0.0, EXTREME_F, 0.5], [0.0, 0.0, 1.0]]], dtype=f64),
            torch.eye(4, dtype=f64)[None],
            1,
            1,
        ),
        0,
    )


def _stack_closed_form(scene: Scene) -> tuple[list[float], float, float]:
    """The contract's compositing loop written out for the stack: rgb, alpha and depth of its one pixel."""
    rgb, T, depth = [0.0, 0.0, 0.0], 1.0, 0.0
    colours = (scene.sh[:, 0] * SH_C0 + 0.5).clamp_min(0.0).tolist()
    for colour, o, z in zip(colours, scene.opacities.tolist(), scene.means[:, 2].tolist(), strict=True):
        a = min(o, ALPHA_MAX)
        if a < ALPHA_MIN:
            continue
        if T * (1 - a) <= TRANSMITTANCE_MIN:
            break
        rgb = [r + T * a * c for r, c in zip(rgb, colour, strict=True)]
        depth += T * a * z
        T *= 1 - a
    return rgb, 1 - T, depth


@pytest.mark.parametrize("opacity", [0.005, 0.3, 0.999])
def test_transmittance_underflow_stack(backend: Rasterizer, device: str, opacity: float) -> None:
    """Thousands of Gaussians stacked on one pixel: the pixel stops where the transmittance would fall to 1e-4
    (faint layers of 0.005: after ~1840 of 2000; opaque ones: after the 2nd), values and gradients finite and equal to
    the contract's compositing loop in float64."""
    scene = _stack_scene(opacity)
    rgb, alpha, depth = _stack_closed_form(scene)
    assert 1e-4 < 1 - alpha < 1e-4 / (1 - min(opacity, ALPHA_MAX)) + 1e-12  # stopped right above the cut-off
    params = [t.to(device, torch.float32).requires_grad_() for t in scene.tensors()]
    out = backend.render(*params, scene.cameras.to(device, torch.float32), sh_degree=0)
    (out.rgb.sum() + out.alpha.sum()).backward()
    assert all_finite(out.rgb, out.alpha, out.depth, *(p.grad for p in params))
    torch.testing.assert_close(_cpu64(out.rgb[0, 0, 0]), torch.tensor(rgb, dtype=torch.float64), atol=5e-5, rtol=0)
    assert abs(float(out.alpha.detach()[0, 0, 0, 0]) - alpha) <= 5e-5
    if out.depth is not None:
        assert abs(float(out.depth.detach()[0, 0, 0, 0]) - depth) <= 5e-5 * max(1.0, depth)


def test_large_image_drawn_in_bands(backend: Rasterizer, device: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """With a pair budget small enough to split the render into row bands, the image and every gradient equal the
    single-band render (the bands only change float rounding of the shifted centres)."""
    import framework.splat.bands as bands

    scene = _on(make_random_scene(12, 40, EXTREME_W, EXTREME_H), device)

    def run() -> tuple[RenderOutput, list[Tensor]]:
        params = [t.clone().requires_grad_() for t in scene.tensors()]
        out = render_scene(backend, scene.with_tensors(params), background=torch.tensor([0.2, 0.3, 0.4], device=device))
        _weighted_loss(out, _loss_weights(out, 3)).backward()
        return out, [p.grad for p in params] + [out.means2d.grad]

    whole, whole_grads = run()
    monkeypatch.setattr(bands, "MAX_PAIRS_PER_BAND", 60)
    box = torch.tensor([[8.0, 6.0]]), torch.tensor([[6.0, 6.0]])
    assert len(bands.row_bands(*box, EXTREME_W, EXTREME_H)) >= 3  # the budget does split such a render
    banded, banded_grads = run()
    for key in ("rgb", "alpha", "depth"):
        if getattr(whole, key) is not None:
            assert within_tolerance_except_jumps(getattr(banded, key), getattr(whole, key), 1e-5, EXTREME_JUMP), key
    for a, b in zip(banded_grads, whole_grads, strict=True):
        if a is not None:
            assert relative_error(a, b) <= 1e-3


_HUGE_RENDER = """
import resource, sys, torch
from framework.testing.conformance import build_backend, make_random_scene, render_scene
from framework.testing.reference import reference_render
backend = build_backend(sys.argv[1])
scene = make_random_scene(0, 8, 4096, 4096, device=sys.argv[2])
m, q, s, o, sh = (t.clone() for t in scene.tensors())
m[0], s[0], o[0] = torch.zeros(3), torch.full((3,), 3.0), torch.tensor(0.5)  # covers the whole image
scene = scene.with_tensors([m, q, s, o, sh])
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
with torch.no_grad():
    out = render_scene(backend, scene)
grown = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 2**20
assert torch.isfinite(out.rgb).all() and out.rgb.shape == (1, 4096, 4096, 3)
c = scene.cameras.to("cpu", torch.float64)
ref = reference_render(*(t.double().cpu() for t in scene.tensors()), c.K, c.world_to_cam, 4096, 4096, 3)["rgb"]
err = (out.rgb.double().cpu() - ref).abs().max().item()
print(f"grown_gib={grown:.2f} err={err:.3g}")
"""


@pytest.mark.slow
def test_4096_image_in_bounded_memory(backend_name: str, device: str) -> None:
    """A 4096 x 4096 render with a Gaussian covering the whole image (16.8 M pairs from it alone) stays finite, needs
    under 3 GiB more than the process held before (row bands), and matches the float64 brute force."""
    proc = subprocess.run(
        [sys.executable, "-c", _HUGE_RENDER, backend_name, device], capture_output=True, text=True, timeout=1800
    )
    if proc.returncode != 0 and "unavailable" in proc.stderr:
        pytest.skip(proc.stderr.strip().splitlines()[-1])
    assert proc.returncode == 0, proc.stderr[-3000:]
    line = proc.stdout.strip().splitlines()[-1]
    values = dict(item.split("=") for item in line.split())
    assert float(values["grown_gib"]) < 3.0, line
    assert float(values["err"]) < 1e-4, line


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_inputs_and_autocast(backend: Rasterizer, device: str, dtype: torch.dtype) -> None:
    """The contract computes in float32: half-precision inputs give the float32 render of the rounded inputs, rounded
    to the input dtype (within one unit in the last place: 2^-8 for bfloat16, 2^-11 for float16, relative), with
    finite gradients in that dtype; under autocast float32 inputs render as without it (within 1e-5)."""
    scene = _on(make_random_scene(4, 50, EXTREME_W, EXTREME_H), device)
    ulp = {torch.float16: 2.0**-11, torch.bfloat16: 2.0**-8}[dtype]
    rounded = [t.to(dtype) for t in scene.tensors()]
    ref = render_scene(backend, scene.with_tensors([t.float() for t in rounded]))
    params = [t.clone().requires_grad_() for t in rounded]
    out = render_scene(backend, scene.with_tensors(params))
    assert out.rgb.dtype == dtype and out.alpha.dtype == dtype
    for key in ("rgb", "alpha"):
        expected = getattr(ref, key)
        bound = ulp * expected.abs().clamp_min(1.0)
        assert bool(((getattr(out, key).float() - expected).abs() <= bound).all()), key
    out.rgb.float().sum().backward()
    assert all(p.grad is not None and p.grad.dtype == dtype and all_finite(p.grad) for p in params)
    plain = render_scene(backend, scene)
    with torch.autocast(torch.device(device).type, dtype=dtype):
        cast = render_scene(backend, scene)
    for key in ("rgb", "alpha"):
        assert float((getattr(cast, key).float() - getattr(plain, key)).abs().max()) <= 1e-5, key

"""The `numba` rasterizer's compiled loops against independent references.

The conformance suite (tests/test_rasterizer_conformance.py) runs this backend too: its gradient tests run the
compiled compositor's backward, and its closed-form tests without gradients the compiled forward. The tests here
check the compiled paths on their own terms:
- in float64 it computes the same function as torch_ref in float64, to summation-order rounding (1e-8);
- in float32, against that float64 render, it is within float32 rounding. The exception is a pixel where a pair
  sits on the 1/255 cut or the 1e-4 termination, and the input rounding puts it on the other side. That pixel then
  moves by at most one pair's weight, under 1/255 (`FLIP_TOL`).
- on the extreme scenes of issue 11 it stays finite, and within the conformance tolerances of the float64 brute force;
- renders that need gradients project and colour the Gaussians with torch_ref's autograd code and composite them
  with compiled loops forward and backward (`framework.kernels.compositing`); their gradients equal torch_ref's
  in float64 to 1e-8 (relative to each tensor's largest entry), and in float32 are within torch_ref's own float32
  error. The conformance suite's finite-difference and extreme-scene gradient tests run on them too.
"""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings

from framework.plugins import load_plugins
from framework.registry import RASTERIZERS
from framework.testing.conformance import (
    EXTREME_JUMP,
    EXTREME_VALUE_TOL,
    extreme_scenes,
    make_random_scene,
    render_scene,
)
from framework.testing.properties import all_finite, within_tolerance_except_jumps
from framework.testing.reference import reference_render

FLOAT64_TOL = 1e-8  # same function, same precision: only the order of sums differs
FLOAT32_TOL = 2e-5  # float32 rounding of inputs and outputs, per pixel, away from the cuts
FLIP_TOL = 1.0 / 255.0  # one pair on the other side of the alpha cut or the termination test
FLIP_FRACTION = 1e-3  # of the pixels, at most this many may sit on a cut


@pytest.fixture(scope="module")
def backends():
    load_plugins()
    return RASTERIZERS.build("numba"), RASTERIZERS.build("torch_ref")


SCENES = [(0, 300, 64, 48, 1, 0), (1, 3000, 96, 80, 3, 3), (2, 1500, 1, 1, 1, 1)]


@pytest.mark.parametrize(("seed", "n", "width", "height", "cameras", "degree"), SCENES)
def test_float64_equals_torch_ref_float64(backends, seed, n, width, height, cameras, degree) -> None:
    numba_backend, torch_ref = backends
    scene = make_random_scene(seed, n, width, height, dtype=torch.float64, num_cameras=cameras, sh_degree=degree)
    bg = torch.tensor([0.2, 0.4, 0.9], dtype=torch.float64)
    with torch.no_grad():
        got = render_scene(numba_backend, scene, background=bg)
        ref = render_scene(torch_ref, scene, background=bg)
    assert got.rgb.dtype == torch.float64 and got.rgb.shape == ref.rgb.shape
    for key in ("rgb", "alpha", "depth", "means2d"):
        torch.testing.assert_close(getattr(got, key), getattr(ref, key), atol=FLOAT64_TOL, rtol=0, msg=key)
    assert torch.equal(got.radii, ref.radii)
    assert float(ref.alpha.max()) > 0.5  # the scenes are not empty


@pytest.mark.parametrize(("seed", "n", "width", "height", "cameras", "degree"), SCENES)
def test_float32_within_rounding_of_float64(backends, seed, n, width, height, cameras, degree) -> None:
    numba_backend, torch_ref = backends
    scene32 = make_random_scene(seed, n, width, height, num_cameras=cameras, sh_degree=degree)
    scene64 = make_random_scene(seed, n, width, height, dtype=torch.float64, num_cameras=cameras, sh_degree=degree)
    with torch.no_grad():
        got = render_scene(numba_backend, scene32)
        ref = render_scene(torch_ref, scene64)
    assert got.rgb.dtype == torch.float32
    for key in ("rgb", "alpha", "depth"):
        err = (getattr(got, key).double() - getattr(ref, key)).abs()
        scale = max(1.0, float(getattr(ref, key).abs().max()))
        assert float(err.max()) <= FLIP_TOL * scale, key
        assert float((err > FLOAT32_TOL * scale).double().mean()) <= FLIP_FRACTION, key
    torch.testing.assert_close(got.means2d.double(), ref.means2d, atol=1e-4, rtol=1e-6)


@settings(max_examples=60, deadline=None)
@given(scene=extreme_scenes())
def test_extremes_finite_and_match_float64_brute_force(backends, scene) -> None:
    """float32 inputs at the extremes (tiny, huge, needle-thin, zero quaternions, at the near plane, behind the camera,
    covering the view): finite outputs within the conformance tolerances of the float64 brute force."""
    numba_backend, _ = backends
    c = scene.cameras
    ref = reference_render(*scene.tensors(), c.K, c.world_to_cam, c.width, c.height, scene.sh_degree)
    with torch.no_grad():
        out = numba_backend.render(
            *(t.float() for t in scene.tensors()), c.to("cpu", torch.float32), sh_degree=scene.sh_degree
        )
    assert all_finite(out.rgb, out.alpha, out.depth, out.means2d)
    assert float(out.alpha.min()) >= 0.0 and float(out.alpha.max()) <= 1.0
    for key in ("rgb", "alpha", "depth"):
        scale = max(1.0, float(ref[key].abs().max())) if key == "depth" else 1.0
        assert within_tolerance_except_jumps(
            getattr(out, key), ref[key], EXTREME_VALUE_TOL * scale, EXTREME_JUMP * scale
        ), key


def _render_and_backward(backend, scene, seed: int, background=None):
    """One render with every output weighted by fixed random images, backward; -> (output, input grads + means2d's)."""
    params = [t.detach().clone().requires_grad_() for t in scene.tensors()]
    out = backend.render(*params, scene.cameras, sh_degree=scene.sh_degree, background=background)
    g = torch.Generator().manual_seed(seed)
    weights = [torch.rand(o.shape, generator=g, dtype=o.dtype) for o in (out.rgb, out.alpha, out.depth)]
    loss = (out.rgb * weights[0]).sum() + (out.alpha * weights[1]).sum() + 0.1 * (out.depth * weights[2]).sum()
    loss.backward()
    return out, [p.grad for p in params] + [out.means2d.grad]


GRAD_NAMES = ("means", "quats", "scales", "opacities", "sh", "means2d")


@pytest.mark.parametrize(("seed", "n", "width", "height", "cameras", "degree"), SCENES)
def test_float64_gradients_equal_torch_ref_float64(backends, seed, n, width, height, cameras, degree) -> None:
    """The compiled compositor's backward (a per-pixel walk back through a log of the pairs) against torch_ref's
    (segmented sums over the sorted pair list): two derivations of the same closed form, in float64."""
    numba_backend, torch_ref = backends
    scene = make_random_scene(seed, n, width, height, dtype=torch.float64, num_cameras=cameras, sh_degree=degree)
    bg = torch.tensor([0.2, 0.4, 0.9], dtype=torch.float64)
    got, got_grads = _render_and_backward(numba_backend, scene, seed, bg)
    ref, ref_grads = _render_and_backward(torch_ref, scene, seed, bg)
    assert got.rgb.grad_fn is not None
    torch.testing.assert_close(got.rgb, ref.rgb, atol=FLOAT64_TOL, rtol=0)
    for name, a, b in zip(GRAD_NAMES, got_grads, ref_grads, strict=True):
        scale = max(1.0, float(b.abs().max()))
        torch.testing.assert_close(a, b, atol=FLOAT64_TOL * scale, rtol=0, msg=name)
        assert float(b.abs().max()) > 0, name  # the gradient is not trivially zero


@pytest.mark.parametrize(("seed", "n", "width", "height", "cameras", "degree"), SCENES[:2])
def test_float32_gradients_within_rounding_of_float64(backends, seed, n, width, height, cameras, degree) -> None:
    """float32 gradients against torch_ref's float64 ones. The compiled compositor works in float64 inside, so its
    error comes from rounding the inputs and the projection's float32 autograd; torch_ref's own float32 gradients
    are the yardstick: ours must be within twice their error, per tensor, relative to its largest entry."""
    numba_backend, torch_ref = backends
    scene32 = make_random_scene(seed, n, width, height, num_cameras=cameras, sh_degree=degree)
    scene64 = make_random_scene(seed, n, width, height, dtype=torch.float64, num_cameras=cameras, sh_degree=degree)
    _, got = _render_and_backward(numba_backend, scene32, seed)
    _, ref32 = _render_and_backward(torch_ref, scene32, seed)
    _, ref64 = _render_and_backward(torch_ref, scene64, seed)
    for name, a, b, c in zip(GRAD_NAMES, got, ref32, ref64, strict=True):
        scale = float(c.abs().max())
        ours, theirs = float((a.double() - c).abs().max()) / scale, float((b.double() - c).abs().max()) / scale
        assert ours <= max(2.0 * theirs, 1e-6), (name, ours, theirs)


def test_gradients_at_clamped_alpha_and_early_termination(backends) -> None:
    """Opacities near 1: most pairs hit the 0.999 clamp (no gradient through sigma or the opacity there) and most
    pixels terminate after a few layers. The float64 gradients still equal torch_ref's."""
    numba_backend, torch_ref = backends
    scene = make_random_scene(9, 600, 40, 32, dtype=torch.float64, sh_degree=1, max_opacity=0.95)
    scene.opacities.copy_(
        0.9999 + 0.0001 * torch.rand(600, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    )
    scene.scales.mul_(30.0)  # wide footprints: sigma < 1e-3 near most centres, where alpha is clamped at 0.999
    got, got_grads = _render_and_backward(numba_backend, scene, 9)
    ref, ref_grads = _render_and_backward(torch_ref, scene, 9)
    assert float(ref.alpha.detach().mean()) > 0.99  # opaque: pixels finish after a few layers
    for name, a, b in zip(GRAD_NAMES, got_grads, ref_grads, strict=True):
        torch.testing.assert_close(a, b, atol=FLOAT64_TOL * max(1.0, float(b.abs().max())), rtol=0, msg=name)


def test_pair_log_grows_when_a_render_has_more_pairs(backends, monkeypatch) -> None:
    """The pair log starts with room for 8 pairs per entry (or the last render's count): a render with far more,
    large Gaussians over the whole image, runs again with room for all, and its gradients are still torch_ref's."""
    from framework.kernels import compositing as compiled_composite

    numba_backend, torch_ref = backends
    monkeypatch.setattr(compiled_composite, "_capacity_hint", [0])
    scene = make_random_scene(5, 40, 64, 64, dtype=torch.float64, sh_degree=0, max_opacity=0.3)
    scene.scales.mul_(8.0)  # radii of tens of pixels: hundreds of pairs per Gaussian
    _, got = _render_and_backward(numba_backend, scene, 5)
    _, ref = _render_and_backward(torch_ref, scene, 5)
    assert compiled_composite._capacity_hint[0] > 8 * 40 * 5  # the log had to grow
    for name, a, b in zip(GRAD_NAMES, got, ref, strict=True):
        torch.testing.assert_close(a, b, atol=FLOAT64_TOL * max(1.0, float(b.abs().max())), rtol=0, msg=name)


def test_unused_outputs_and_an_empty_image(backends) -> None:
    """A loss on the depth alone, or on nothing the Gaussians reach, still gives torch_ref's gradients (zeros and
    a filled means2d.grad where nothing is drawn), as densification expects."""
    numba_backend, torch_ref = backends
    scene = make_random_scene(6, 100, 32, 24, dtype=torch.float64, sh_degree=0)
    grads = []
    for backend in (numba_backend, torch_ref):
        params = [t.detach().clone().requires_grad_() for t in scene.tensors()]
        out = backend.render(*params, scene.cameras, sh_degree=0)
        out.means2d.retain_grad()
        out.depth.sum().backward()
        grads.append([p.grad for p in params[:3]] + [out.means2d.grad])
    for a, b in zip(*grads, strict=True):
        torch.testing.assert_close(a, b, atol=1e-8, rtol=0)
    faint = [t.detach().clone().requires_grad_() for t in scene.tensors()]
    out = numba_backend.render(*faint[:3], faint[3] * 0.001, faint[4], scene.cameras, sh_degree=0)  # all culled
    out.means2d.retain_grad()
    out.rgb.sum().backward()
    assert out.means2d.grad is not None and float(out.means2d.grad.abs().max()) == 0.0
    assert float(out.alpha.detach().max()) == 0.0


def test_compiled_projection_gradients_equal_autograd_through_project_gaussians() -> None:
    """The hand-written projection backward against autograd through `project_gaussians`, float64, three cameras:
    Gaussians past the field-of-view clamp (its slope is 0 there), zero and tiny quaternions, needle-thin scales."""
    from framework.kernels.projection import project_compiled
    from framework.splat.projection import project_gaussians

    scene = make_random_scene(8, 400, 48, 40, dtype=torch.float64, num_cameras=3, sh_degree=0)
    means = scene.means.detach().clone()
    means[:60] *= 4.0  # far outside the view: culled, or kept by a large box past the clamp
    scales = scene.scales.detach().clone()
    scales[:60] *= 20.0
    scales[60:70, 0] *= 1e-4  # needles
    quats = scene.quats.detach().clone()
    quats[70:75] = 0.0  # the identity, a constant
    quats[75:80] *= 1e-9
    cams = scene.cameras
    outs, grads = [], []
    for project in (project_compiled, project_gaussians):
        params = [t.clone().requires_grad_() for t in (means, quats, scales)]
        p = project(*params, scene.opacities, cams.K, cams.world_to_cam, cams.width, cams.height, 0.01, 1e10)
        valid = p.valid
        w = [
            torch.rand(t.shape, generator=torch.Generator().manual_seed(i), dtype=t.dtype)
            for i, t in enumerate((p.means2d, p.conics, p.depths))
        ]
        loss = ((p.means2d * w[0]).sum(-1) + (p.conics * w[1]).sum(-1) + p.depths * w[2])[valid].sum()
        loss.backward()
        outs.append(p)
        grads.append([t.grad for t in params])
    got, ref = outs
    assert torch.equal(got.valid, ref.valid) and torch.equal(got.radii, ref.radii)
    size = torch.tensor([cams.width, cams.height], dtype=torch.float64)
    past = ((got.means2d < -0.15 * size) | (got.means2d > 1.15 * size)).any(-1)  # centre beyond the widened view
    assert int((got.valid & past).sum()) >= 3  # kept by their boxes: the clamp's zero slope is exercised
    for key in ("means2d", "conics", "depths", "half_extents"):
        v = got.valid
        torch.testing.assert_close(getattr(got, key)[v], getattr(ref, key)[v], atol=1e-9, rtol=1e-9, msg=key)
    for name, a, b in zip(("means", "quats", "scales"), *grads, strict=True):
        assert torch.isfinite(a).all(), name
        torch.testing.assert_close(a, b, atol=1e-9 * max(1.0, float(b.abs().max())), rtol=1e-9, msg=name)
    assert float(grads[0][1][70:75].abs().max()) == 0.0  # zero quaternions: no gradient

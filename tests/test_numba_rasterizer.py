"""The `numba` rasterizer's compiled forward pass against independent references.

The conformance suite (tests/test_rasterizer_conformance.py) runs this backend too. There, every test that asks for
gradients is handed to torch_ref, and the closed-form tests without gradients run the compiled loops. The tests here
check the compiled path on its own terms:
- in float64 it computes the same function as torch_ref in float64, to summation-order rounding (1e-8);
- in float32, against that float64 render, it is within float32 rounding. The exception is a pixel where a pair
  sits on the 1/255 cut or the 1e-4 termination, and the input rounding puts it on the other side. That pixel then
  moves by at most one pair's weight, under 1/255 (`FLIP_TOL`).
- on the extreme scenes of issue 11 it stays finite, and within the conformance tolerances of the float64 brute force;
- renders that need gradients are torch_ref's own, so training and densification see no difference.
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
        out = numba_backend.render(*(t.float() for t in scene.tensors()), c.to("cpu", torch.float32),
                                   sh_degree=scene.sh_degree)  # fmt: skip
    assert all_finite(out.rgb, out.alpha, out.depth, out.means2d)
    assert float(out.alpha.min()) >= 0.0 and float(out.alpha.max()) <= 1.0
    for key in ("rgb", "alpha", "depth"):
        scale = max(1.0, float(ref[key].abs().max())) if key == "depth" else 1.0
        assert within_tolerance_except_jumps(getattr(out, key), ref[key], EXTREME_VALUE_TOL * scale,
                                             EXTREME_JUMP * scale), key  # fmt: skip


def test_gradient_renders_are_torch_refs(backends) -> None:
    """With inputs that require gradients the render is torch_ref's: the same values, a graph, means2d.grad filled."""
    numba_backend, torch_ref = backends
    scene = make_random_scene(4, 200, 40, 30, sh_degree=1)
    outs, grads = [], []
    for backend in (numba_backend, torch_ref):
        params = [t.clone().requires_grad_() for t in scene.tensors()]
        out = backend.render(*params, scene.cameras, sh_degree=scene.sh_degree)
        out.means2d.retain_grad()
        (out.rgb.square().sum() + out.alpha.sum()).backward()
        outs.append(out)
        grads.append([p.grad for p in params] + [out.means2d.grad])
    assert outs[0].rgb.grad_fn is not None
    assert torch.equal(outs[0].rgb, outs[1].rgb)
    for a, b in zip(*grads, strict=True):
        assert torch.equal(a, b)

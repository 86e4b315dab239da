"""The `jax` rasterizer: DLPack bridge, shape buckets (bounded recompiles), parity with `torch_ref` in values and
gradients (every input and means2d), float64 finite differences, and numerical extremes.

Scenes are kept small (<= 256 Gaussians, <= 1024 pairs) so every test reuses the same compiled shapes; the shared
conformance suite (tests/test_rasterizer_conformance.py) covers the rest of the contract.
"""

from __future__ import annotations

import pytest
import torch

jax = pytest.importorskip("jax")

from framework.plugins import load_plugins  # noqa: E402
from framework.registry import RASTERIZERS  # noqa: E402
from framework.splat.jax_raster import composite, project  # noqa: E402
from framework.types import Cameras  # noqa: E402
from plugins.rasterizer.jax_backend import (  # noqa: E402
    MIN_GAUSSIAN_BUCKET,
    bucket,
    to_jax,
    to_torch,
)

load_plugins()


def make_scene(n=24, size=24, cams=2, dtype=torch.float32, seed=0, sh_degree=3, scale=0.08):
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g) * 1.2 - 0.6
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * scale + 0.02
    opac = torch.rand(n, generator=g) * 0.8 + 0.1
    sh = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g) * 0.3
    K = torch.tensor([[size * 1.2, 0.0, size / 2], [0.0, size * 1.1, size / 2 + 0.3], [0.0, 0.0, 1.0]])
    w2c = torch.eye(4).repeat(cams, 1, 1)
    w2c[:, 2, 3] = 3.0
    for c in range(1, cams):  # a small rotation about y and a shift per extra camera
        a = 0.2 * c
        w2c[c, 0, 0], w2c[c, 0, 2], w2c[c, 2, 0], w2c[c, 2, 2] = (
            torch.cos(torch.tensor(a)),
            torch.sin(torch.tensor(a)),
            -torch.sin(torch.tensor(a)),
            torch.cos(torch.tensor(a)),
        )
        w2c[c, 0, 3] = 0.1 * c
    params = [x.to(dtype) for x in (means, quats, scales, opac, sh)]
    return params, Cameras(K.expand(cams, 3, 3).to(dtype), w2c.to(dtype), size, size)


def render_with_grads(name, params, cams, sh_degree=3, background=None, **kw):
    r = RASTERIZERS.build(name, **kw)
    ps = [p.clone().requires_grad_(True) for p in params]
    out = r.render(*ps, cams, sh_degree=sh_degree, background=background)
    H, W = cams.height, cams.width
    wr = torch.linspace(0.2, 1.0, H * W * 3, dtype=out.rgb.dtype).reshape(1, H, W, 3)
    loss = (out.rgb * wr).sum() + (out.alpha * wr[..., :1]).sum() * 0.7 + 0.05 * out.depth.sum()
    loss.backward()
    return out, [p.grad for p in ps]


def rel_err(a, b):
    return float((a.detach() - b.detach()).abs().max() / b.detach().abs().max().clamp_min(1e-12))


# --------------------------------------------------------------------------------------------------------------


def test_registered_and_available():
    assert "jax" in RASTERIZERS.names()
    assert RASTERIZERS.entry("jax").unavailable_reason() is None


def test_bucket_bounds_padding_and_count():
    seen = set()
    for n in range(1, 5000, 7):
        b = bucket(n, MIN_GAUSSIAN_BUCKET)
        assert b >= n
        assert b >= MIN_GAUSSIAN_BUCKET
        if n > MIN_GAUSSIAN_BUCKET:
            assert b <= 1.25 * n + 1, (n, b)
        seen.add(b)
    # 256 .. 5000 spans a bit over 4 octaves: at most 4 shapes per octave
    assert len(seen) <= 4 * 5


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.int32])
def test_dlpack_round_trip(dtype):
    jdev = jax.devices("cpu")[0]
    t = (torch.arange(60, dtype=torch.float64) * 0.37).to(dtype).reshape(5, 12)
    with jax.enable_x64(True):
        a = to_jax(t, jdev)
        assert a.shape == (5, 12)
        back = to_torch(a, torch.device("cpu"))
    assert back.dtype == dtype
    assert torch.equal(back, t)
    # non-contiguous input is copied into a contiguous array with the same values
    tt = t.t()
    with jax.enable_x64(True):
        assert torch.equal(to_torch(to_jax(tt, jdev), torch.device("cpu")), tt)


def test_dlpack_is_zero_copy_on_cpu_for_aligned_tensors():
    jdev = jax.devices("cpu")[0]
    t = torch.empty(4096, dtype=torch.float32)
    t.copy_(torch.arange(4096, dtype=torch.float32))
    a = to_jax(t, jdev)
    if a.unsafe_buffer_pointer() != t.data_ptr():
        pytest.skip("this torch/jaxlib pair copies on import (alignment); values are still checked above")
    back = to_torch(a, torch.device("cpu"))
    assert back.data_ptr() == t.data_ptr()


def test_parity_with_torch_ref_values_and_all_gradients():
    params, cams = make_scene()
    bg = torch.tensor([0.1, 0.2, 0.3])
    ref, ref_g = render_with_grads("torch_ref", params, cams, background=bg)
    out, out_g = render_with_grads("jax", params, cams, background=bg)
    assert float(ref.alpha.detach().mean()) > 0.05  # the scene actually covers pixels
    for f in ("rgb", "alpha", "depth"):
        assert rel_err(getattr(out, f), getattr(ref, f)) <= 1e-4, f
    assert torch.equal(out.radii, ref.radii)
    assert out.means2d.shape == ref.means2d.shape
    assert torch.allclose(out.means2d, ref.means2d, rtol=1e-6, atol=1e-4)
    for name, g, r in zip(("means", "quats", "scales", "opacities", "sh"), out_g, ref_g, strict=True):
        assert g is not None and torch.isfinite(g).all(), name
        assert rel_err(g, r) <= 1e-3, name
    assert out.means2d.grad is not None
    assert float(out.means2d.grad.abs().max()) > 0
    assert rel_err(out.means2d.grad, ref.means2d.grad) <= 1e-3


def test_means2d_grad_is_the_screen_space_gradient():
    """means2d.grad must equal dL/d(means2d): check it by finite differences on the compositing step alone."""
    params, cams = make_scene(n=6, seed=3, scale=0.15)
    out, _ = render_with_grads("jax", params, cams)
    g = out.means2d.grad  # [C, N, 2]
    c, i = (out.radii > 0).nonzero()[0].tolist()
    # loss as a function of a shifted screen position of one Gaussian, through the same JAX compositor
    from plugins.rasterizer.jax_backend import build_pairs, pad_pairs

    ps = [p.double() for p in params]
    jdev = jax.devices("cpu")[0]
    with jax.enable_x64(True):
        args = [to_jax(x, jdev) for x in ps]
        sh_j = args[4]
        (m2d, con, dep, col), (half, radii) = project(
            args[0],
            args[1],
            args[2],
            sh_j,
            args[3],
            to_jax(cams.world_to_cam.double(), jdev),
            to_jax(cams.K.double(), jdev),
            0.01,
            1e10,
            width=cams.width,
            height=cams.height,
            sh_degree=3,
        )
        t = lambda a: to_torch(a, torch.device("cpu"))  # noqa: E731
        gi, pi = build_pairs(t(m2d), t(con), t(dep), t(half), t(radii), ps[3], cams.width, cams.height)
        npx = cams.num * cams.height * cams.width
        gi, pi, st = pad_pairs(gi, pi, npx)
        C, N = radii.shape
        H, W = cams.height, cams.width
        wr = jax.numpy.asarray(torch.linspace(0.2, 1.0, H * W * 3, dtype=torch.float64).reshape(H * W, 3).numpy())

        def loss(m):
            rgb, alpha, depth = composite(
                m.reshape(-1, 2),
                con.reshape(-1, 3),
                dep.reshape(-1),
                col.reshape(-1, 3),
                jax.numpy.broadcast_to(args[3], (C, N)).reshape(-1),
                jax.numpy.zeros(3),
                to_jax(gi, jdev),
                to_jax(pi, jdev),
                to_jax(st, jdev).astype(bool),
                num_pixels=npx,
                width=W,
                height=H,
            )
            rgb = rgb.reshape(C, H * W, 3)
            return (rgb * wr).sum() + (alpha.reshape(C, H * W) * wr[:, 0]).sum() * 0.7 + 0.05 * depth.sum()

        for axis in (0, 1):
            e = jax.numpy.zeros_like(m2d).at[c, i, axis].set(1e-5)
            fd = (float(loss(m2d + e)) - float(loss(m2d - e))) / 2e-5
            assert abs(fd - float(g[c, i, axis])) <= 1e-3 * max(1.0, abs(fd)), (axis, fd, float(g[c, i, axis]))


def test_float64_gradcheck():
    params, cams = make_scene(n=3, size=10, cams=1, dtype=torch.float64, seed=1, sh_degree=1, scale=0.2)
    r = RASTERIZERS.build("jax")
    wr = torch.linspace(0.2, 1.0, 10 * 10 * 3, dtype=torch.float64).reshape(1, 10, 10, 3)

    def f(means, quats, scales, opac, sh):
        out = r.render(means, quats, scales, opac, sh, cams, sh_degree=1)
        return (out.rgb * wr).sum(), out.alpha.sum(), out.depth.sum()

    inputs = tuple(p.clone().requires_grad_(True) for p in params)
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_recompiles_bounded_when_n_changes():
    """Densification changes N every few hundred steps; N inside one bucket must not recompile."""
    r = RASTERIZERS.build("jax")

    def render(n, seed):
        params, cams = make_scene(n=n, seed=seed)
        params[0][8:, 2] = -10.0  # all but a few behind the camera: the pair count stays in one bucket
        with torch.no_grad():
            return r.render(*params, cams, sh_degree=3)

    render(200, 0)  # N bucket 256
    before = (project._cache_size(), composite._cache_size())
    for n in (131, 177, 255, 256):
        out = render(n, n)
        assert out.means2d.shape == (2, n, 2) and out.radii.shape == (2, n)
        assert int((out.radii > 0).sum()) > 0
    assert (project._cache_size(), composite._cache_size()) == before
    assert r.compiled_shapes == 2  # one projection and one compositing shape


def test_empty_scene_gives_background():
    params, cams = make_scene(n=0)
    bg = torch.tensor([0.3, 0.5, 0.7])
    out = RASTERIZERS.build("jax").render(*params, cams, sh_degree=3, background=bg)
    assert torch.allclose(out.rgb, bg.expand_as(out.rgb))
    assert torch.count_nonzero(out.alpha) == 0 and torch.count_nonzero(out.depth) == 0
    assert out.means2d.shape == (2, 0, 2) and out.radii.shape == (2, 0)


def test_extremes_stay_finite():
    params, cams = make_scene(n=12, seed=5)
    means, quats, scales, opac, sh = params
    quats[0] = 0.0  # zero quaternion -> identity
    quats[1] = torch.tensor([1e-20, 0.0, 0.0, 1e-20])
    scales[2] = 1e-8  # tiny
    scales[3] = 50.0  # covers the whole image
    opac[4] = torch.sigmoid(torch.tensor(30.0))  # 1.0 in float32 -> alpha clamped at 0.999
    opac[5] = torch.sigmoid(torch.tensor(-30.0))  # culled by the box rule
    means[6] = torch.tensor([0.0, 0.0, -5.0])  # behind the camera
    means[7] = torch.tensor([0.0, 0.0, -3.0 + 0.01])  # exactly at the near plane of camera 0
    means[8] = torch.tensor([0.0, 0.0, -3.0])  # at the camera centre (SH direction zero)
    out, grads = render_with_grads("jax", params, cams)
    for t in (out.rgb, out.alpha, out.depth, out.means2d, out.means2d.grad, *grads):
        assert torch.isfinite(t).all()
    assert int(out.radii[0, 5]) == 0 and int(out.radii[0, 6]) == 0 and int(out.radii[0, 7]) == 0
    ref, ref_g = render_with_grads("torch_ref", params, cams)
    assert rel_err(out.rgb, ref.rgb) <= 1e-4
    for g, r in zip(grads, ref_g, strict=True):
        assert rel_err(g, r) <= 1e-3


def test_no_grad_matches_grad_path():
    params, cams = make_scene(seed=7)
    r = RASTERIZERS.build("jax")
    with torch.no_grad():
        a = r.render(*params, cams, sh_degree=3)
    b = r.render(*[p.clone().requires_grad_(True) for p in params], cams, sh_degree=3)
    assert torch.allclose(a.rgb, b.rgb, atol=1e-6) and torch.equal(a.radii, b.radii)

"""The `gsplat` rasterizer: availability logic and output mapping on CPU (gsplat itself is substituted by a fake
that returns tensors of gsplat 1.5.3's documented shapes, so these test our glue), and parity with `torch_ref` on a
CUDA machine (`-m gpu`)."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from framework.plugins import load_plugins
from framework.registry import RASTERIZERS, ComponentUnavailableError
from framework.types import Cameras
from plugins.rasterizer import gsplat_backend
from plugins.rasterizer.gsplat_backend import REASON_NO_CUDA, REASON_NOT_INSTALLED, GsplatRasterizer

load_plugins()


def make_scene(n=40, size=32, cams=2, seed=0, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g) * 1.2 - 0.6
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.08 + 0.02
    opac = torch.rand(n, generator=g) * 0.8 + 0.1
    sh = torch.randn(n, 16, 3, generator=g) * 0.3
    K = torch.tensor([[size * 1.2, 0.0, size / 2], [0.0, size * 1.1, size / 2 + 0.3], [0.0, 0.0, 1.0]])
    w2c = torch.eye(4).repeat(cams, 1, 1)
    w2c[:, 2, 3] = 3.0
    w2c[1:, 0, 3] = 0.2
    params = [x.to(device) for x in (means, quats, scales, opac, sh)]
    return params, Cameras(K.expand(cams, 3, 3).to(device), w2c.to(device), size, size)


def test_unavailable_without_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert RASTERIZERS.entry("gsplat").unavailable_reason() == REASON_NO_CUDA
    with pytest.raises(ComponentUnavailableError) as info:
        RASTERIZERS.build("gsplat")
    assert REASON_NO_CUDA in str(info.value) and "gsplat" in str(info.value)


def test_not_installed_reason(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(gsplat_backend.importlib.util, "find_spec", lambda name: None)
    assert RASTERIZERS.entry("gsplat").unavailable_reason() == REASON_NOT_INSTALLED


def test_importing_the_plugin_does_not_import_gsplat():
    code = (
        "import sys; import plugins.rasterizer.gsplat_backend as m; "
        "from framework.registry import RASTERIZERS; RASTERIZERS.entry('gsplat').unavailable_reason(); "
        "print('gsplat' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    if torch.cuda.is_available():
        pytest.skip("with a CUDA device the availability check imports gsplat on purpose")
    assert out.stdout.strip() == "False"


class FakeRasterization:
    """Returns gsplat 1.5.3-shaped outputs from simple functions of the inputs, and records the call."""

    def __init__(self, radii_per_axis: bool = True):
        self.calls: list[dict] = []
        self.radii_per_axis = radii_per_axis

    def __call__(self, means, quats, scales, opacities, colors, viewmats, Ks, width, height, **kw):
        self.calls.append({"args": (means, quats, scales, opacities, colors, viewmats, Ks, width, height), **kw})
        C, N = viewmats.shape[0], means.shape[0]
        means2d = means[None, :, :2] * 10.0 + torch.arange(C, dtype=means.dtype)[:, None, None]  # [C, N, 2]
        base = means2d.sum() + opacities.sum() + colors.sum()
        render = torch.ones(C, height, width, 4) * base  # [C, H, W, 4] = RGB + accumulated depth
        render = render + torch.arange(4, dtype=means.dtype)  # channel c holds base + c
        alphas = torch.full((C, height, width, 1), 0.25)
        r = torch.arange(C * N, dtype=torch.int32).reshape(C, N)
        radii = torch.stack([r, r + 1], dim=-1) if self.radii_per_axis else r  # [C, N, 2] in 1.5.3
        return render, alphas, {"means2d": means2d, "radii": radii}


@pytest.mark.parametrize("radii_per_axis", [True, False])
def test_output_mapping_with_fake_gsplat(monkeypatch, radii_per_axis):
    fake = FakeRasterization(radii_per_axis)
    monkeypatch.setattr(gsplat_backend, "_rasterization", lambda: fake)
    monkeypatch.setattr(gsplat_backend, "_warned_compile", True)
    params, cams = make_scene(n=5)
    ps = [p.clone().requires_grad_(True) for p in params]
    bg = torch.tensor([0.1, 0.2, 0.3])
    out = GsplatRasterizer().render(*ps, cams, sh_degree=2, background=bg, near=0.05, far=50.0)

    call = fake.calls[0]
    assert call["sh_degree"] == 2 and call["render_mode"] == "RGB+D" and call["packed"] is False
    assert call["near_plane"] == 0.05 and call["far_plane"] == 50.0 and call["eps2d"] == 0.3
    assert call["rasterize_mode"] == "classic"
    assert call["backgrounds"].shape == (2, 3) and torch.equal(call["backgrounds"][1], bg)
    assert call["args"][4].shape == (5, 16, 3)  # SH coefficients passed as colours
    assert torch.equal(call["args"][5], cams.world_to_cam) and torch.equal(call["args"][6], cams.K)
    assert call["args"][7:] == (32, 32)

    assert out.rgb.shape == (2, 32, 32, 3) and out.alpha.shape == (2, 32, 32, 1) and out.depth.shape == (2, 32, 32, 1)
    base = float(out.rgb.detach()[0, 0, 0, 0])
    assert torch.allclose(out.rgb[0, 0, 0], torch.tensor([base, base + 1, base + 2]))
    assert float(out.depth.detach()[0, 0, 0, 0]) == pytest.approx(base + 3)  # the 4th channel is the depth
    assert torch.all(out.alpha == 0.25)
    expect_r = torch.arange(10, dtype=torch.int32).reshape(2, 5) + (1 if radii_per_axis else 0)
    assert out.radii.dtype == torch.int32 and torch.equal(out.radii, expect_r)

    # means2d keeps its gradient after backward, and gradients reach the Gaussian parameters through it
    (out.means2d[..., 0] * 2.0).sum().backward()
    assert out.means2d.grad is not None and torch.all(out.means2d.grad[..., 0] == 2.0)
    assert torch.allclose(ps[0].grad[:, 0], torch.full((5,), 2.0 * 10.0 * 2))


def test_packed_mode_scatters_into_camera_by_gaussian(monkeypatch):
    cam = torch.tensor([0, 0, 1])
    gid = torch.tensor([1, 3, 3])

    def fake(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **kw):
        assert kw["packed"] is True
        m = means[gid, :2] * 10.0  # [nnz, 2]
        info = {"camera_ids": cam, "gaussian_ids": gid, "means2d": m, "radii": torch.tensor([[2, 3], [4, 1], [5, 5]])}
        C = viewmats.shape[0]
        return torch.zeros(C, height, width, 4) + m.sum(), torch.zeros(C, height, width, 1), info

    monkeypatch.setattr(gsplat_backend, "_rasterization", lambda: fake)
    monkeypatch.setattr(gsplat_backend, "_warned_compile", True)
    params, cams = make_scene(n=4)
    ps = [p.clone().requires_grad_(True) for p in params]
    out = GsplatRasterizer(packed=True).render(*ps, cams, sh_degree=0)
    expect = torch.zeros(2, 4, dtype=torch.int32)
    expect[0, 1], expect[0, 3], expect[1, 3] = 3, 4, 5
    assert torch.equal(out.radii, expect)
    assert torch.allclose(out.means2d.detach()[1, 3], params[0][3, :2] * 10.0)
    assert torch.all(out.means2d.detach()[1, :3] == 0)
    out.rgb.sum().backward()
    assert out.means2d.grad is not None
    assert torch.all(out.means2d.grad[0, 1] == 2 * 32 * 32 * 3) and torch.all(out.means2d.grad[0, 0] == 0)


def test_float64_inputs_are_passed_as_float32_and_cast_back(monkeypatch):
    fake = FakeRasterization()
    monkeypatch.setattr(gsplat_backend, "_rasterization", lambda: fake)
    monkeypatch.setattr(gsplat_backend, "_warned_compile", True)
    params, cams = make_scene(n=3)
    out = GsplatRasterizer().render(*[p.double() for p in params], cams.to("cpu", torch.float64), sh_degree=0)
    assert all(a.dtype == torch.float32 for a in fake.calls[0]["args"][:7])
    assert out.rgb.dtype == torch.float64


def test_first_call_warns_about_compilation(monkeypatch):
    monkeypatch.setattr(gsplat_backend, "_rasterization", lambda: FakeRasterization())
    monkeypatch.setattr(gsplat_backend, "_warned_compile", False)
    params, cams = make_scene(n=3)
    with pytest.warns(RuntimeWarning, match="compiles"):
        GsplatRasterizer().render(*params, cams, sh_degree=0)


# ------------------------------------------------------------------------------------------------ GPU parity


def _loss(out, H, W):
    wr = torch.linspace(0.2, 1.0, H * W * 3, device=out.rgb.device).reshape(1, H, W, 3)
    return (out.rgb * wr).sum() + 0.7 * (out.alpha * wr[..., :1]).sum() + 0.05 * out.depth.sum()


def _rel(a, b):
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-12))


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("sh_degree", [0, 3])
def test_gpu_parity_with_torch_ref(sh_degree):
    params, cams = make_scene(n=300, size=64, device="cuda")
    bg = torch.tensor([0.1, 0.2, 0.3], device="cuda")
    res = {}
    for name in ("torch_ref", "gsplat"):
        ps = [p.clone().requires_grad_(True) for p in params]
        out = RASTERIZERS.build(name).render(*ps, cams, sh_degree=sh_degree, background=bg)
        _loss(out, 64, 64).backward()
        res[name] = (out, [p.grad for p in ps])
    (ref, ref_g), (out, out_g) = res["torch_ref"], res["gsplat"]
    assert float(ref.alpha.mean()) > 0.05
    for f in ("rgb", "alpha", "depth"):
        assert _rel(getattr(out, f).detach(), getattr(ref, f).detach()) <= 1e-4, f
    vis = ref.radii > 0
    assert torch.equal(out.radii > 0, vis)
    assert (out.radii - ref.radii).abs().max() <= 1  # per-axis ceil vs ceil of the max agree to a pixel
    assert torch.allclose(out.means2d[vis], ref.means2d[vis], atol=1e-3)
    for name, g, r in zip(("means", "quats", "scales", "opacities", "sh"), out_g, ref_g, strict=True):
        assert _rel(g, r) <= 1e-3, name
    assert _rel(out.means2d.grad[vis], ref.means2d.grad[vis]) <= 1e-3


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_gpu_empty_scene_and_culling():
    params, cams = make_scene(n=4, size=32, device="cuda")
    params[0][:] = torch.tensor([0.0, 0.0, -10.0], device="cuda")  # everything behind the camera
    bg = torch.tensor([0.3, 0.5, 0.7], device="cuda")
    out = RASTERIZERS.build("gsplat").render(*params, cams, sh_degree=3, background=bg)
    assert torch.allclose(out.rgb, bg.expand_as(out.rgb)) and torch.all(out.radii == 0)

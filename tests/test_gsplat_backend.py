"""The `gsplat` rasterizer: availability logic, output mapping and the wrapper's fixes for gsplat's behaviour.

On CPU, gsplat's `rasterization` is replaced by `FakeGsplat`, which reproduces what gsplat 1.5.3's source does in the
cases the wrapper handles (unwritten `means2d` rows, NaN covariances from zero quaternions, Gaussians kept on the
near/far planes, packed rows, `absgrad`, bare shape asserts). The behaviour tests take a `device` fixture whose `cuda`
parameter (`-m gpu`) runs them on gsplat itself, next to the parity tests against `torch_ref`."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from torch import Tensor

from framework.interfaces.rasterizer import NEAR_PLANE
from framework.plugins import load_plugins
from framework.registry import RASTERIZERS, ComponentUnavailableError
from framework.types import Cameras
from plugins.rasterizer import gsplat_backend
from plugins.rasterizer.gsplat_backend import REASON_NO_CUDA, REASON_NOT_INSTALLED, GsplatRasterizer
from tests.helpers import float32_ops as f32

load_plugins()

NEEDS_CUDA = {"condition": not torch.cuda.is_available(), "reason": "needs a CUDA device"}


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


ALPHA_THRESHOLD = 1.0 / 255.0


def _rotmat_as_gsplat(quats: Tensor) -> Tensor:
    """[N, 4] wxyz float64 holding float32 values -> [N, 3, 3] as `quat_to_rotmat` in gsplat's Utils.cuh, in exactly
    rounded float32 (`tests/helpers/float32_ops.py`): scaled by rsqrt(|q|^2) with no guard, so a zero quaternion
    (0 * inf) or an underflowing one (|q|^2 -> 0, then inf - inf) gives NaN. rsqrt is 1 / sqrt, each rounded."""
    w, x, y, z = quats.unbind(-1)  # [N]
    norm2 = f32.add(f32.add(f32.add(f32.mul(x, x), f32.mul(y, y)), f32.mul(z, z)), f32.mul(w, w))
    inv_norm = f32.div(1.0, f32.f32(norm2.sqrt()))
    w, x, y, z = (f32.mul(v, inv_norm) for v in (w, x, y, z))
    x2, y2, z2 = f32.mul(x, x), f32.mul(y, y), f32.mul(z, z)
    xy, xz, yz = f32.mul(x, y), f32.mul(x, z), f32.mul(y, z)
    wx, wy, wz = f32.mul(w, x), f32.mul(w, y), f32.mul(w, z)

    def one_minus_twice(s: Tensor) -> Tensor:
        return f32.sub(1.0, f32.mul(2.0, s))

    def twice(a: Tensor, b: Tensor, sign: float) -> Tensor:
        return f32.mul(2.0, f32.add(a, b) if sign > 0 else f32.sub(a, b))

    rows = [
        [one_minus_twice(f32.add(y2, z2)), twice(xy, wz, -1), twice(xz, wy, +1)],
        [twice(xy, wz, +1), one_minus_twice(f32.add(x2, z2)), twice(yz, wx, -1)],
        [twice(xz, wy, -1), twice(yz, wx, +1), one_minus_twice(f32.add(x2, y2))],
    ]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)  # [N, 3, 3]


def _conics_as_gsplat(quats, scales, R, t, means, fx, fy, cx, cy, width, height, near, far, eps2d):
    """The covariance chain of `projection_ewa_3dgs_fused_fwd_kernel` (ProjectionEWA3DGSFused.cu) in exactly rounded
    float32, each operation in the kernel's order, so it gives the same bits on every CPU (tests/helpers/float32_ops;
    nvcc's FMA contraction is not emulated): quat_scale_to_covar_preci, covarW2C, persp_proj, add_blur,
    glm::inverse. -> (camera-space mean [C, N, 3], blurred 2D covariance [C, N, 2, 2], det [C, N], conics
    [C, N, 3]), all float64 tensors holding float32 values; rows outside [near, far] get z = 1 for the projection, as
    the kernel returns before dividing by their depth (and no inf reaches the gradients)."""
    d = torch.float64
    quats, scales, R, t, means = (v.to(d) for v in (quats, scales, R, t, means))
    M = f32.mul(_rotmat_as_gsplat(quats), scales[:, None, :])  # [N, 3, 3] R S: one non-zero product per entry
    covar = f32.matmul(M, M.transpose(-1, -2))  # [N, 3, 3]
    Rc = R[:, None]  # [C, 1, 3, 3]
    covar_c = f32.matmul(f32.matmul(Rc, covar[None]), Rc.transpose(-1, -2))  # [C, N, 3, 3]
    mean_c = f32.add(f32.matmul(Rc, means[None, :, :, None])[..., 0], t[:, None])  # [C, N, 3]
    x, y, z = mean_c.unbind(-1)  # [C, N]
    z = torch.where((z < near) | (z > far), torch.ones_like(z), z)
    fx, fy, cx, cy = (v.to(d) for v in (fx, fy, cx, cy))  # [C, 1]
    tan_fovx, tan_fovy = f32.div(f32.mul(0.5, float(width)), fx), f32.div(f32.mul(0.5, float(height)), fy)
    lim_x_pos = f32.add(f32.div(f32.sub(float(width), cx), fx), f32.mul(0.3, tan_fovx))
    lim_x_neg = f32.add(f32.div(cx, fx), f32.mul(0.3, tan_fovx))
    lim_y_pos = f32.add(f32.div(f32.sub(float(height), cy), fy), f32.mul(0.3, tan_fovy))
    lim_y_neg = f32.add(f32.div(cy, fy), f32.mul(0.3, tan_fovy))
    rz = f32.div(1.0, z)
    rz2 = f32.mul(rz, rz)
    tx = f32.mul(z, torch.minimum(lim_x_pos, torch.maximum(-lim_x_neg, f32.mul(x, rz))))
    ty = f32.mul(z, torch.minimum(lim_y_pos, torch.maximum(-lim_y_neg, f32.mul(y, rz))))
    zero = torch.zeros_like(z)
    J = torch.stack(
        [f32.mul(fx, rz), zero, f32.mul(f32.mul(-fx, tx), rz2), zero, f32.mul(fy, rz), f32.mul(f32.mul(-fy, ty), rz2)],
        -1,
    ).reshape(*z.shape, 2, 3)
    cov = f32.matmul(f32.matmul(J, covar_c), J.transpose(-1, -2))  # [C, N, 2, 2]
    a, c = f32.add(cov[..., 0, 0], eps2d), f32.add(cov[..., 1, 1], eps2d)  # add_blur
    b01, b10 = cov[..., 0, 1], cov[..., 1, 0]  # glm: m[1][0] is row 0, column 1
    cov = torch.stack([torch.stack([a, b01], -1), torch.stack([b10, c], -1)], -2)
    det = f32.sub(f32.mul(a, c), f32.mul(b01, b10))  # glm::inverse: m[0][0] m[1][1] - m[1][0] m[0][1]
    inv_det = f32.div(1.0, det)
    conics = torch.stack([f32.mul(c, inv_det), f32.mul(-b10, inv_det), f32.mul(a, inv_det)], -1)  # [C, N, 3]
    return mean_c, cov, det, conics


def _project_as_gsplat(means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane, eps2d):
    """`projection_ewa_3dgs_fused_fwd_kernel` (ProjectionEWA3DGSFused.cu) in torch: -> (culled [C, N], radii
    [C, N, 2] int32, means2d [C, N, 2], depths [C, N], conics [C, N, 3]), values of culled rows unspecified. The
    covariance and conic are exactly rounded float32 (`_conics_as_gsplat`: tests/test_conic_precision.py measures
    their rounding, which must not depend on the CPU)."""
    near, far = (torch.tensor(v, dtype=torch.float32) for v in (near_plane, far_plane))  # C++ `float` parameters
    R, t = viewmats[:, :3, :3], viewmats[:, :3, 3]  # [C, 3, 3], [C, 3]
    fx, fy, cx, cy = Ks[:, 0, 0, None], Ks[:, 1, 1, None], Ks[:, 0, 2, None], Ks[:, 1, 2, None]  # [C, 1]
    mean_c, cov, det, conics = _conics_as_gsplat(
        quats, scales, R, t, means, fx, fy, cx, cy, width, height, float(near), float(far), eps2d
    )
    mean_c, cov, det, conics = (v.to(torch.float32) for v in (mean_c, cov, det, conics))
    x, y, z = mean_c.unbind(-1)  # [C, N]
    depth_culled = (z < near) | (z > far)  # the kernel keeps z == near and z == far
    z = torch.where(depth_culled, torch.ones_like(z), z)  # the kernel returns before dividing by these
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], -1)  # [C, N, 2]
    a, c = cov[..., 0, 0], cov[..., 1, 1]
    with torch.no_grad():
        op = opacities.expand_as(z)
        extend = torch.sqrt(2.0 * torch.log(op.clamp_min(ALPHA_THRESHOLD) / ALPHA_THRESHOLD)).clamp_max(3.33)
        rad = torch.stack([torch.ceil(extend * a.sqrt()), torch.ceil(extend * c.sqrt())], -1)  # [C, N, 2]
        mx, my, rx, ry = means2d[..., 0], means2d[..., 1], rad[..., 0], rad[..., 1]
        outside = (mx + rx <= 0) | (mx - rx >= width) | (my + ry <= 0) | (my - ry >= height)
        culled = depth_culled | (det <= 0) | (op < ALPHA_THRESHOLD) | ((rx <= 0) & (ry <= 0)) | outside
        # (int32_t) of a NaN radius (NaN covariance: every test above is False for it) is 0 on CUDA
        radii = torch.where(culled[..., None], 0.0, rad.nan_to_num(nan=0.0, posinf=2.0**31 - 1)).to(torch.int32)
    return culled, radii, means2d, z, conics


class _FakeRasterizeToPixels(torch.autograd.Function):
    """Stands in for gsplat's `_RasterizeToPixels`: saves means2d for backward, reads only the rows it draws, and with
    `absgrad` sets `.absgrad` (sum over pixels of |per-pixel d loss / d means2d|) on that saved tensor. Its image is a
    simple differentiable function: every drawn row adds o * f * colour to all pixels of its image, with
    f = 1 + 0.01 x + 0.02 y + 0.001 (conic_a + conic_c); alpha = 0.01 * sum of o."""

    @staticmethod
    def image(means2d, conics, colors, opacities, rows, image_ids, n_images, height, width, backgrounds):
        m = means2d.reshape(-1, 2)[rows]  # [R, 2]
        q = conics.reshape(-1, 3)[rows]
        o = opacities.reshape(-1)[rows]
        col = colors.reshape(-1, colors.shape[-1])[rows]  # [R, D]
        f = 1 + 0.01 * m[:, 0] + 0.02 * m[:, 1] + 0.001 * (q[:, 0] + q[:, 2])
        sums = col.new_zeros(n_images, col.shape[-1]).index_add(0, image_ids, (o * f)[:, None] * col)  # [I, D]
        alpha = (0.01 * o.new_zeros(n_images).index_add(0, image_ids, o)).clamp_max(0.999)  # [I]
        render = sums[:, None, None, :] + ((1 - alpha)[:, None] * backgrounds)[:, None, None, :]
        return render.expand(-1, height, width, -1), alpha[:, None, None, None].expand(-1, height, width, 1)

    @staticmethod
    def forward(
        ctx, means2d, conics, colors, opacities, backgrounds, rows, image_ids, n_images, height, width, absgrad
    ):
        ctx.save_for_backward(means2d, conics, colors, opacities, backgrounds, rows, image_ids)
        ctx.shape, ctx.absgrad = (n_images, height, width), absgrad
        render, alpha = _FakeRasterizeToPixels.image(
            means2d, conics, colors, opacities, rows, image_ids, n_images, height, width, backgrounds
        )
        return render.contiguous(), alpha.contiguous()

    @staticmethod
    def backward(ctx, v_render, v_alpha):
        means2d, conics, colors, opacities, backgrounds, rows, image_ids = ctx.saved_tensors
        with torch.enable_grad():
            xs = [t.detach().requires_grad_() for t in (means2d, conics, colors, opacities)]
            outs = _FakeRasterizeToPixels.image(*xs, rows, image_ids, *ctx.shape, backgrounds)
            grads = torch.autograd.grad(outs, xs, (v_render, v_alpha), allow_unused=True)
        if ctx.absgrad:
            o = opacities.reshape(-1)[rows]
            col = colors.reshape(-1, colors.shape[-1])[rows]  # [R, D]
            per_pixel = (v_render[image_ids] * col[:, None, None, :]).sum(-1).abs().sum((1, 2))  # [R]
            absgrad = torch.zeros_like(means2d).reshape(-1, 2)
            absgrad[rows] = (o * per_pixel)[:, None] * torch.tensor([0.01, 0.02])
            means2d.absgrad = absgrad.reshape(means2d.shape)
        return (*grads, None, None, None, None, None, None, None)


class FakeGsplat:
    """gsplat 1.5.3's `rasterization` on CPU, as far as this wrapper can tell the difference (read from rendering.py,
    cuda/_wrapper.py and ProjectionEWA3DGS{Fused,Packed}.cu), and a record of every call:
    - the shape `assert`s of rendering.py;
    - the projection kernel's rules (`_project_as_gsplat`): a Gaussian on the near or far plane is kept, a zero
      quaternion gives a NaN covariance and a radius of 0, per-axis radii;
    - `means2d` comes from `at::empty` and culled rows are never written: they hold NaN here;
    - packed mode: rows of the (camera, Gaussian) pairs that pass the kernel's tests, camera-major;
    - a Gaussian is drawn only if both radii are > 0 (`isect_tiles`); colours are clamp(SH + 0.5, 0);
      `render_mode="RGB+D"` appends the depth channel and a 0 background for it;
    - `absgrad` lands on the means2d tensor the rasterizer saved (see `_FakeRasterizeToPixels`).
    """

    def __init__(self, radii_per_axis: bool = True):
        self.calls: list[dict] = []
        self.radii_per_axis = radii_per_axis
        self.last: tuple | None = None

    def __call__(self, means, quats, scales, opacities, colors, viewmats, Ks, width, height, **kw):
        self.calls.append({"args": (means, quats, scales, opacities, colors, viewmats, Ks, width, height), **kw})
        N, C = means.shape[-2], viewmats.shape[-3]
        # gsplat 1.5.3's projection computes means.numel() / (N * 3) on the host: N = 0 is SIGFPE (seen on an H200)
        assert N > 0, "gsplat 1.5.3 kills the process (SIGFPE) on a scene with no Gaussians"
        assert means.shape == (N, 3), means.shape
        assert quats.shape == (N, 4), quats.shape
        assert scales.shape == (N, 3), scales.shape
        assert opacities.shape == (N,), opacities.shape
        assert viewmats.shape == (C, 4, 4), viewmats.shape
        assert Ks.shape == (C, 3, 3), Ks.shape
        assert colors.dim() == 3 and colors.shape[0] == N and colors.shape[-1] == 3, colors.shape
        assert (kw["sh_degree"] + 1) ** 2 <= colors.shape[-2], colors.shape
        assert kw["render_mode"] == "RGB+D"
        culled, radii, means2d, depths, conics = _project_as_gsplat(
            means, quats, scales, opacities, viewmats, Ks, width, height, kw["near_plane"], kw["far_plane"], kw["eps2d"]
        )
        # SH colour, clamp(SH + 0.5, 0); the degree-0 term is enough here (no test reads the view dependence)
        rgb = (0.28209479177387814 * colors[None, :, 0, :] + 0.5).clamp_min(0.0).expand(C, N, 3)  # [C, N, 3]
        feats = torch.cat([rgb, depths[..., None]], -1)  # [C, N, 4]
        info: dict = {}
        if kw["packed"]:
            cam, gid = torch.nonzero(~culled, as_tuple=True)  # [nnz] camera-major
            means2d, radii, conics, depths = means2d[cam, gid], radii[cam, gid], conics[cam, gid], depths[cam, gid]
            feats, op = feats[cam, gid], opacities[gid]
            info.update(camera_ids=cam, gaussian_ids=gid)
            image_of_row = cam
        else:
            means2d = torch.where(culled[..., None], torch.full_like(means2d, float("nan")), means2d)  # at::empty
            op = opacities.expand(C, N)
            image_of_row = torch.arange(C)[:, None].expand(C, N).reshape(-1)
        rows = torch.nonzero((radii > 0).all(-1).reshape(-1)).squeeze(1)  # what isect_tiles keeps
        bg = torch.zeros(C, 4) if kw["backgrounds"] is None else torch.cat([kw["backgrounds"], torch.zeros(C, 1)], -1)
        render, alphas = _FakeRasterizeToPixels.apply(
            means2d, conics, feats, op, bg, rows, image_of_row[rows], C, height, width, kw["absgrad"]
        )
        if not kw["packed"] and not self.radii_per_axis:
            radii = radii.amax(-1)  # [C, N] in gsplat before 1.5
        info.update(means2d=means2d, radii=radii, depths=depths, conics=conics)
        self.last = (render, alphas, info)
        return render, alphas, info


@pytest.fixture
def fake(monkeypatch) -> FakeGsplat:
    f = FakeGsplat()
    monkeypatch.setattr(gsplat_backend, "_rasterization", lambda: f)
    monkeypatch.setattr(gsplat_backend, "_warned_compile", True)
    return f


@pytest.fixture(params=["fake", pytest.param("cuda", marks=[pytest.mark.gpu, pytest.mark.skipif(**NEEDS_CUDA)])])
def device(request, monkeypatch) -> str:
    """Where a behaviour test runs: on CPU against `FakeGsplat`, or (`-m gpu`) on a CUDA device against gsplat."""
    if request.param == "fake":
        monkeypatch.setattr(gsplat_backend, "_rasterization", lambda: FakeGsplat())
        monkeypatch.setattr(gsplat_backend, "_warned_compile", True)
        return "cpu"
    return "cuda"


@pytest.mark.parametrize("radii_per_axis", [True, False])
def test_output_mapping_with_fake_gsplat(monkeypatch, radii_per_axis):
    fake = FakeGsplat(radii_per_axis)
    monkeypatch.setattr(gsplat_backend, "_rasterization", lambda: fake)
    monkeypatch.setattr(gsplat_backend, "_warned_compile", True)
    params, cams = make_scene(n=5)
    params[0][0] = torch.tensor([0.0, 0.0, -10.0])  # behind both cameras
    ps = [p.clone().requires_grad_(True) for p in params]
    bg = torch.tensor([0.1, 0.2, 0.3])
    out = GsplatRasterizer().render(*ps, cams, sh_degree=2, background=bg, near=0.05, far=50.0)

    call = fake.calls[0]
    assert call["sh_degree"] == 2 and call["render_mode"] == "RGB+D" and call["packed"] is False
    assert call["eps2d"] == 0.3 and call["rasterize_mode"] == "classic"
    assert call["backgrounds"].shape == (2, 3) and torch.equal(call["backgrounds"][1], bg)
    assert call["args"][4].shape == (5, 16, 3)  # SH coefficients passed as colours
    assert torch.equal(call["args"][5], cams.world_to_cam) and torch.equal(call["args"][6], cams.K)
    assert call["args"][7:] == (32, 32)

    render, alphas, info = fake.last
    assert out.rgb.shape == (2, 32, 32, 3) and out.alpha.shape == (2, 32, 32, 1) and out.depth.shape == (2, 32, 32, 1)
    assert torch.equal(out.rgb, render[..., :3]) and torch.equal(out.depth, render[..., 3:4])  # 4th channel: depth
    assert torch.equal(out.alpha, alphas)
    r = info["radii"]
    expect_r = torch.where((r > 0).all(-1), r.amax(-1), 0) if radii_per_axis else r
    assert out.radii.dtype == torch.int32 and torch.equal(out.radii, expect_r.int()) and bool((out.radii > 0).any())

    # means2d keeps its gradient after backward, and gradients reach the Gaussian parameters through it:
    # d(means2d_x)/d(mean_x) = fx / z for every camera that draws the Gaussian (R = I, z = mean_z + 3), else 0
    (out.means2d[..., 0] * 2.0).sum().backward()
    assert out.means2d.grad is not None and torch.all(out.means2d.grad[..., 0] == 2.0)
    drawn = (out.radii > 0).float()  # [C, N]
    assert drawn[:, 0].sum() == 0 and drawn[:, 1:].sum() > 0
    expected = (2.0 * 32 * 1.2 / (params[0][:, 2] + 3.0) * drawn).sum(0)
    torch.testing.assert_close(ps[0].grad[:, 0], expected)


def test_culled_means2d_rows_are_zero(device):
    """Rows of culled Gaussians (behind the camera, off screen) are 0, not gsplat's unwritten memory; the others are
    the projected centres (torch_ref's), and backward still fills means2d.grad."""
    params, cams = make_scene(n=30, device=device)
    params[0][:4] = torch.tensor([[0.0, 0.0, -10.0], [50.0, 0.0, 0.0], [0.0, -50.0, 0.0], [0.1, 0.1, -3.0]])
    ps = [p.clone().requires_grad_(True) for p in params]
    out = GsplatRasterizer().render(*ps, cams, sh_degree=3)
    ref = RASTERIZERS.build("torch_ref").render(*params, cams, sh_degree=3)
    drawn = ref.radii > 0
    assert torch.equal(out.radii > 0, drawn) and not bool(drawn[:, :4].any()) and bool(drawn.any())
    assert torch.isfinite(out.means2d).all()
    assert float(out.means2d.detach()[~drawn].abs().max()) == 0.0
    torch.testing.assert_close(out.means2d.detach()[drawn], ref.means2d[drawn], atol=1e-4, rtol=0)
    out.rgb.sum().backward()
    assert out.means2d.grad is not None and torch.isfinite(out.means2d.grad).all()
    assert float(out.means2d.grad[drawn].abs().sum()) > 0


def test_zero_and_underflowing_quaternions_render_as_identity(device):
    """A zero quaternion and one of 1e-30 (|q|^2 underflows in float32) are drawn with the identity rotation, as the
    contract (torch_ref) says, not dropped: same radii and image as with (1, 0, 0, 0), finite gradients."""
    params, cams = make_scene(n=12, device=device)
    identity = params[1].clone()
    identity[:2] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    params[1][0], params[1][1] = 0.0, 1e-30
    assert bool((RASTERIZERS.build("torch_ref").render(*params, cams, sh_degree=3).radii[:, :2] > 0).all())
    ps = [p.clone().requires_grad_(True) for p in params]
    out = GsplatRasterizer().render(*ps, cams, sh_degree=3)
    ref = GsplatRasterizer().render(params[0], identity, *params[2:], cams, sh_degree=3)
    assert torch.equal(out.radii, ref.radii) and bool((out.radii[:, :2] > 0).all())
    torch.testing.assert_close(out.rgb, ref.rgb, atol=1e-6, rtol=0)
    (out.rgb.sum() + out.alpha.sum()).backward()
    assert all(torch.isfinite(p.grad).all() for p in ps)


def test_gaussians_exactly_on_the_near_and_far_planes_are_culled(device):
    """The contract culls z <= near and z >= far; gsplat culls z < near and z > far. A Gaussian exactly on a plane
    (in float32) is culled, the next float32 inside is drawn, as in torch_ref."""
    K = torch.tensor([[[40.0, 0.0, 16.0], [0.0, 40.0, 16.0], [0.0, 0.0, 1.0]]])
    cams = Cameras(K, torch.eye(4)[None], 32, 32).to(device)  # world = camera, so z is the mean's z exactly
    inf = torch.tensor(float("inf"))
    for near, far in ((0.5, 2.0), (NEAR_PLANE, 2.0)):
        n32, f32 = torch.tensor(near), torch.tensor(far)  # the planes as float32 depths
        z = torch.stack([n32, torch.nextafter(n32, inf), f32, torch.nextafter(f32, -inf)])
        means = torch.stack([torch.zeros(4), torch.zeros(4), z], -1)  # [4, 3] on the optical axis
        params = [
            means,
            torch.tensor([[1.0, 0, 0, 0]]).repeat(4, 1),
            z[:, None].repeat(1, 3) * 0.05,
            torch.full((4,), 0.9),
            torch.full((4, 1, 3), 0.5),
        ]
        params = [p.to(device) for p in params]
        out = GsplatRasterizer().render(*params, cams, sh_degree=0, near=near, far=far)
        ref = RASTERIZERS.build("torch_ref").render(*params, cams, sh_degree=0, near=near, far=far)
        assert (ref.radii[0] > 0).tolist() == [False, True, False, True], (near, far)
        assert (out.radii[0] > 0).tolist() == [False, True, False, True], (near, far)


def test_packed_mode_matches_unpacked_and_carries_absgrad(device):
    """packed=True gives the same radii, image and gradients as packed=False; the dense means2d is a detached leaf
    whose .grad and .absgrad (AbsGS) are the unpacked ones."""
    params, cams = make_scene(n=30, device=device)
    params[0][0] = torch.tensor([0.0, 0.0, -10.0])  # culled in both cameras
    res = {}
    for packed in (False, True):
        ps = [p.clone().requires_grad_(True) for p in params]
        out = GsplatRasterizer(packed=packed, absgrad=True).render(*ps, cams, sh_degree=3)
        w = torch.linspace(-1.0, 1.0, out.rgb.numel(), device=device).reshape(out.rgb.shape)
        ((out.rgb * w).sum() + out.alpha.sum()).backward()
        res[packed] = out, ps
    (dense, dense_ps), (ref, ref_ps) = res[True], res[False]
    assert torch.equal(dense.radii, ref.radii) and bool((ref.radii > 0).any())
    torch.testing.assert_close(dense.rgb, ref.rgb)
    drawn = ref.radii > 0
    torch.testing.assert_close(dense.means2d.detach()[drawn], ref.means2d.detach()[drawn])
    tol = {"rtol": 1e-4, "atol": 1e-6}  # gsplat accumulates gradients with atomics, in an order that varies
    assert dense.means2d.is_leaf and dense.means2d.grad is not None
    torch.testing.assert_close(dense.means2d.grad, ref.means2d.grad, **tol)
    assert getattr(dense.means2d, "absgrad", None) is not None, "absgrad did not reach the dense means2d"
    torch.testing.assert_close(dense.means2d.absgrad, ref.means2d.absgrad, **tol)
    assert float(ref.means2d.absgrad[drawn].abs().sum()) > 0 and float(dense.means2d.absgrad[~drawn].abs().max()) == 0
    for a, b in zip(dense_ps, ref_ps, strict=True):
        torch.testing.assert_close(a.grad, b.grad, **tol)


@pytest.mark.parametrize(
    "index, shape, name",
    [(0, (6, 2), "means"), (1, (6, 3), "quats"), (2, (5, 3), "scales"), (3, (6, 1), "opacities"), (4, (6, 3, 3), "sh")],
)
def test_bad_shapes_are_reported_before_gsplat_runs(device, index, shape, name):
    """Shapes are checked as torch_ref checks them (a ValueError naming the argument), not by gsplat's bare asserts."""
    params, cams = make_scene(n=6, device=device)
    params[index] = torch.zeros(shape, device=device)
    with pytest.raises(ValueError, match=f"'{name}'"):
        GsplatRasterizer().render(*params, cams, sh_degree=2)


def test_inputs_reach_gsplat_contiguous(fake):
    """gsplat's CUDA entry points reject strided tensors (CHECK_INPUT); 1.5.3's Python wrappers copy them first, the
    wrapper does not rely on that."""
    params, cams = make_scene(n=6)
    params[0] = params[0].t().contiguous().t()  # same values, column-major
    params[4] = params[4].transpose(0, 1).contiguous().transpose(0, 1)
    cams = Cameras(cams.K[:1].expand(2, 3, 3), cams.world_to_cam, cams.width, cams.height)
    GsplatRasterizer().render(*params, cams, sh_degree=3)
    assert all(a.is_contiguous() for a in fake.calls[0]["args"][:7])


def test_scene_without_gaussians_renders_the_background_and_back_propagates(device):
    """N = 0 never reaches gsplat (FakeGsplat refuses it as gsplat 1.5.3's SIGFPE would): the image is the
    background, alpha and depth are 0, and a loss over the outputs back-propagates to empty gradients."""
    _, cams = make_scene(n=1, device=device)
    ps = [torch.zeros(*shape, device=device, requires_grad=True) for shape in ((0, 3), (0, 4), (0, 3), (0,), (0, 4, 3))]
    bg = torch.tensor([0.3, 0.5, 0.7], device=device)
    out = GsplatRasterizer().render(*ps, cams, sh_degree=1, background=bg)
    C, H, W = cams.num, cams.height, cams.width
    assert torch.equal(out.rgb.detach(), bg.expand(C, H, W, 3))
    assert float(out.alpha.detach().abs().max()) == 0.0 and float(out.depth.detach().abs().max()) == 0.0
    assert out.means2d.shape == (C, 0, 2) and out.radii.shape == (C, 0)
    _loss(out, H, W).backward()
    assert all(p.grad is not None and p.grad.shape == p.shape for p in ps)
    black = GsplatRasterizer().render(*[p.detach() for p in ps], cams, sh_degree=1)
    assert float(black.rgb.abs().max()) == 0.0


def test_float64_inputs_are_passed_as_float32_and_cast_back(fake):
    params, cams = make_scene(n=3)
    out = GsplatRasterizer().render(*[p.double() for p in params], cams.to("cpu", torch.float64), sh_degree=0)
    assert all(a.dtype == torch.float32 for a in fake.calls[0]["args"][:7])
    assert out.rgb.dtype == torch.float64


def test_first_call_warns_about_compilation(monkeypatch):
    monkeypatch.setattr(gsplat_backend, "_rasterization", lambda: FakeGsplat())
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

"""`framework.image.ssim.ssim_map` as compiled loops (numba) with a hand-written backward, for CPU training steps.

Why: after its filter was compiled (`framework.kernels.separable_filter`), the D-SSIM term of a CPU step was still
about seventy torch operations over [1, 3, H, W] maps: the five moments, the
means' and variances' combination, and their gradients, each a pass of its own with its dispatch. Per pixel that is
a few dozen flops. Here each image plane's moments, filter, map and, backward, the map's gradient to the five filtered
moments, the filter's adjoint and the chain rule to both images are loops over that plane; the planes are split
between the threads (the loops release the GIL).

The same definitions as `ssim_map` (kornia's): moments x, y, x^2, y^2, xy filtered by the separable window with
reflected borders; mu1 = F x, mu2 = F y, s11 = F x^2 - mu1^2, s22 = F y^2 - mu2^2, s12 = F xy - mu1 mu2;
SSIM = (2 mu1 mu2 + c1)(2 s12 + c2) / ((mu1^2 + mu2^2 + c1)(s11 + s22 + c2) + eps). The filter sums in the images'
dtype, the per-pixel combination in float64, stored in the images' dtype.
`tests/test_compiled_ssim.py` compares values and gradients with kornia's SSIM in float64 and by finite differences.
"""

from __future__ import annotations

import torch
from numba import njit
from torch import Tensor

from framework.image.ssim import gaussian_window, ssim_constants
from framework.kernels.separable_filter import filter_planes
from framework.kernels.threads import run_chunked

#: pixels (over an image plane's five moments) below which a chunk of planes is not worth a second thread
MIN_PIXELS_PER_CHUNK = 32768


@njit(cache=True, nogil=True)
def ssim_forward(x, y, taps, c1, c2, eps, start, stop, moments, work, filtered, out) -> None:
    """Planes start..stop of x, y [P, H, W] -> the SSIM map out [P, H, W]; keeps the filtered moments filtered
    [P, 5, H, W] (mu1, mu2, F x^2, F y^2, F xy) for the backward. moments and work [P, 5, H, W] are scratch."""
    H, W = x.shape[1], x.shape[2]
    for p in range(start, stop):
        m = moments[p]
        for i in range(H):
            for j in range(W):
                a, b = x[p, i, j], y[p, i, j]
                m[0, i, j], m[1, i, j], m[2, i, j], m[3, i, j], m[4, i, j] = a, b, a * a, b * b, a * b
        filter_planes(m, taps, taps, False, 0, 5, work[p], filtered[p])
        f = filtered[p]
        for i in range(H):
            for j in range(W):
                mu1, mu2 = f[0, i, j], f[1, i, j]
                mu11, mu22, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
                num = (2.0 * mu12 + c1) * (2.0 * (f[4, i, j] - mu12) + c2)
                den = (mu11 + mu22 + c1) * ((f[2, i, j] - mu11) + (f[3, i, j] - mu22) + c2)
                out[p, i, j] = num / (den + eps)


@njit(cache=True, nogil=True)
def ssim_backward(x, y, taps, c1, c2, eps, filtered, grad_map, start, stop, grad_f, work, grad_m, grad_x, grad_y):
    """The gradients of planes start..stop: grad_map [P, H, W] -> grad_x, grad_y [P, H, W], from the forward's
    filtered moments. grad_f, work and grad_m [P, 5, H, W] are scratch (the gradients at the filtered moments and at
    the moments before the filter)."""
    H, W = x.shape[1], x.shape[2]
    for p in range(start, stop):
        f, gf = filtered[p], grad_f[p]
        for i in range(H):
            for j in range(W):
                mu1, mu2 = f[0, i, j], f[1, i, j]
                mu11, mu22, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
                a1 = 2.0 * mu12 + c1  # SSIM = a1 b1 / (a2 b2 + eps)
                b1 = 2.0 * (f[4, i, j] - mu12) + c2
                a2 = mu11 + mu22 + c1
                b2 = (f[2, i, j] - mu11) + (f[3, i, j] - mu22) + c2
                inv = 1.0 / (a2 * b2 + eps)
                g = grad_map[p, i, j]
                g_a1, g_b1 = g * b1 * inv, g * a1 * inv
                g_den = -g * a1 * b1 * inv * inv
                g_a2, g_b2 = g_den * b2, g_den * a2
                # a1 = 2 mu1 mu2 + c1; b1 = 2 (F xy - mu1 mu2) + c2; a2 = mu1^2 + mu2^2 + c1;
                # b2 = F x^2 - mu1^2 + F y^2 - mu2^2 + c2
                gf[0, i, j] = 2.0 * (mu2 * (g_a1 - g_b1) + mu1 * (g_a2 - g_b2))
                gf[1, i, j] = 2.0 * (mu1 * (g_a1 - g_b1) + mu2 * (g_a2 - g_b2))
                gf[2, i, j] = g_b2
                gf[3, i, j] = g_b2
                gf[4, i, j] = 2.0 * g_b1
        filter_planes(gf, taps, taps, True, 0, 5, work[p], grad_m[p])
        gm = grad_m[p]
        for i in range(H):
            for j in range(W):
                a, b = x[p, i, j], y[p, i, j]
                grad_x[p, i, j] = gm[0, i, j] + 2.0 * a * gm[2, i, j] + b * gm[4, i, j]
                grad_y[p, i, j] = gm[1, i, j] + 2.0 * b * gm[3, i, j] + a * gm[4, i, j]


def _min_planes(h: int, w: int) -> int:
    """Image planes per thread chunk, from MIN_PIXELS_PER_CHUNK (a 128 x 128 RGB image splits 1 + 2)."""
    return -(-MIN_PIXELS_PER_CHUNK // max(1, 5 * h * w))


class _CompiledSSIM(torch.autograd.Function):
    """(img1, img2 [B, C, H, W]) -> SSIM map [B, C, H, W]; differentiable in both images."""

    @staticmethod
    def forward(ctx, img1, img2, taps, c1, c2, eps):  # type: ignore[override]
        B, C, H, W = img1.shape
        x = img1.detach().reshape(B * C, H, W).contiguous()
        y = img2.detach().to(img1.dtype).reshape(B * C, H, W).contiguous()
        P = B * C
        out = torch.empty_like(x)
        filtered = x.new_empty(P, 5, H, W)
        scratch = (x.new_empty(P, 5, H, W).numpy(), x.new_empty(P, 5, H, W).numpy())
        args = (x.numpy(), y.numpy(), taps, c1, c2, eps)
        run_chunked(ssim_forward, args, (*scratch, filtered.numpy(), out.numpy()), P, min_chunk=_min_planes(H, W))
        ctx.save_for_backward(x, y, filtered)
        ctx.constants = (taps, c1, c2, eps)
        ctx.img2_dtype = img2.dtype
        return out.reshape(B, C, H, W)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_map):  # type: ignore[override]
        x, y, filtered = ctx.saved_tensors
        P, H, W = x.shape
        g = grad_map.to(x.dtype).reshape(P, H, W).contiguous()
        grad_x, grad_y = torch.empty_like(x), torch.empty_like(y)
        scratch = tuple(x.new_empty(P, 5, H, W).numpy() for _ in range(3))
        args = (x.numpy(), y.numpy(), *ctx.constants, filtered.numpy(), g.numpy())
        run_chunked(ssim_backward, args, (*scratch, grad_x.numpy(), grad_y.numpy()), P, min_chunk=_min_planes(H, W))
        shape = grad_map.shape
        grad_img2 = grad_y.reshape(shape).to(ctx.img2_dtype) if ctx.needs_input_grad[1] else None
        return grad_x.reshape(shape), grad_img2, None, None, None, None


def ssim_map_compiled(img1: Tensor, img2: Tensor, kernel: Tensor, c1: float, c2: float, eps: float) -> Tensor:
    """SSIM map [B, C, H, W] of CPU float32/float64 images [B, C, H, W] with the 1-D window kernel
    [1, K] along both axes; K odd, K // 2 below both sides (as the filter requires)."""
    taps = kernel.detach().reshape(-1).to(device="cpu", dtype=img1.dtype).numpy()
    K, (H, W) = taps.shape[0], img1.shape[-2:]
    if K % 2 == 0 or K // 2 >= min(H, W):
        raise ValueError(f"ssim_map_compiled: a {K}-tap window on {H} x {W} images; it needs K odd and K // 2 < H, W.")
    return _CompiledSSIM.apply(img1, img2, taps, float(c1), float(c2), float(eps))


def ssim_map(img1: Tensor, img2: Tensor, window_size: int, max_val: float = 1.0, eps: float = 1e-12) -> Tensor:
    """`framework.image.ssim.ssim_map` (same signature, window and constants) of CPU float32/float64 images."""
    c1, c2 = ssim_constants(max_val)
    return ssim_map_compiled(img1, img2, gaussian_window(window_size, img1.dtype, img1.device), c1, c2, eps)

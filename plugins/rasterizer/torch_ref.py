"""`torch_ref`: the pure-PyTorch rasterizer, the reference every other backend is compared with.

It works on the list of (Gaussian, pixel) pairs inside each projected footprint rather than on tiles: on a CPU the
padding and per-tile sorts of a tiled renderer cost far more than they save. Per frame:
1. enumerate, for every Gaussian (entries sorted by depth), the pixels of each box row that lie inside the ellipse
   where alpha can reach 1/255 (closed-form span per row, so almost no pair is wasted);
2. one stable integer sort by pixel puts the pairs in (pixel, depth) order;
3. composite every pixel with a segmented cumulative sum of log(1 - alpha) in float64 (a float32 running sum over
   millions of pairs would lose the per-pixel digits), which also gives the early-termination prefix;
4. per-pixel sums are segment sums over the sorted pairs.
A custom autograd function does the compositing backward in closed form from a second segmented sum (the effect of
each alpha on the pairs behind it), keeping only per-pair indices, offsets, alpha and transmittance from forward.
The per-pair arithmetic lives in four small functions that `compile=True` hands to `torch.compile`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from framework.interfaces.rasterizer import (
    ALPHA_MAX,
    ALPHA_MIN,
    BOX_MARGIN,
    FAR_PLANE,
    LOG_T_MIN,
    NEAR_PLANE,
    Rasterizer,
    check_render_inputs,
)
from framework.registry import register
from framework.splat.bands import row_bands
from framework.splat.projection import project_gaussians
from framework.splat.sh import eval_sh
from framework.types import Cameras, RenderOutput


def _to_index(x: Tensor, lo: int, hi: int) -> Tensor:
    """Float pixel bounds (may be +-inf or NaN at the extremes) -> int64 clamped to [lo, hi]; NaN -> lo."""
    return torch.nan_to_num(x, nan=float(lo), posinf=float(hi), neginf=float(lo)).clamp(lo, hi).long()


def enumerate_pairs(
    means2d: Tensor,  # [M, 2] (detached, unshifted)
    conics: Tensor,  # [M, 3] (detached)
    opacities: Tensor,  # [M] (detached, all >= 1/255)
    half: Tensor,  # [M, 2] box half extents in pixels
    cam: Tensor,  # [M] camera index of each entry
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """Every (entry, pixel) pair whose pixel centre may have alpha >= 1/255 -> (entry [P], flat pixel [P]).

    Rows come from the screen box; within a row the pixels come from the exact span of the ellipse
    sigma <= ln(255 * opacity) (widened by BOX_MARGIN), so hardly any enumerated pair is wasted. Pairs come out
    entry-major, so entries given in depth order give pairs in depth order.
    """
    dev = means2d.device
    M = means2d.shape[0]
    y0 = _to_index(torch.ceil(means2d[:, 1] - half[:, 1] - BOX_MARGIN - 0.5), 0, height)
    y1 = _to_index(torch.floor(means2d[:, 1] + half[:, 1] + BOX_MARGIN - 0.5), -1, height - 1)
    nrows = (y1 - y0 + 1).clamp_min(0)  # [M]
    R = int(nrows.sum())
    r_ent = torch.repeat_interleave(torch.arange(M, device=dev), nrows, output_size=R)  # [R]
    r_y = (
        y0.index_select(0, r_ent)
        + torch.arange(R, device=dev)
        - (torch.cumsum(nrows, 0) - nrows).index_select(0, r_ent)
    )
    dy = means2d[:, 1].index_select(0, r_ent) - (r_y.to(means2d.dtype) + 0.5)
    a, b, c = (conics[:, i].index_select(0, r_ent) for i in range(3))
    L = torch.log((opacities.index_select(0, r_ent) / ALPHA_MIN).clamp_min(1.0))
    disc = (b * dy) ** 2 - a * (c * dy * dy - 2.0 * L)  # sigma(dx) <= L is a quadratic in dx
    sq = torch.sqrt(disc.clamp_min(0.0))
    a_safe = a.clamp_min(torch.finfo(a.dtype).tiny)
    mx = means2d[:, 0].index_select(0, r_ent)
    x0 = _to_index(torch.ceil(mx - (-b * dy + sq) / a_safe - BOX_MARGIN - 0.5), 0, width)
    x1 = _to_index(torch.floor(mx - (-b * dy - sq) / a_safe + BOX_MARGIN - 0.5), -1, width - 1)
    n = torch.where(disc >= 0, (x1 - x0 + 1).clamp_min(0), torch.zeros_like(x0))  # [R]
    P = int(n.sum())
    p_row = torch.repeat_interleave(torch.arange(R, device=dev), n, output_size=P)  # [P]
    row_base = (cam.index_select(0, r_ent) * height + r_y) * width + x0 - (torch.cumsum(n, 0) - n)  # [R]
    pix = row_base.index_select(0, p_row) + torch.arange(P, device=dev)
    ent = r_ent.index_select(0, p_row)
    return ent, pix


def pair_alpha(
    mx: Tensor, my: Tensor, ca: Tensor, cb: Tensor, cc: Tensor, op: Tensor, ent: Tensor, pix: Tensor, width: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Per pair (dx, dy, alpha) with d = mean2d - pixel centre and the contribution rule applied:
    alpha = min(0.999, opacity * exp(-sigma)), or 0 where that is below 1/255 or sigma < 0.

    Entry columns are [M] (means shifted by camera * height along y, so that row = pix // width works for every
    camera).
    """
    # row/column through float64 (exact for any realistic pixel count; int64 division does not vectorise)
    pf = pix.to(torch.float64)
    row = torch.floor((pf + 0.5) * (1.0 / width))
    col = pf - row * width
    dx = mx.index_select(0, ent) - (col + 0.5).to(mx.dtype)
    dy = my.index_select(0, ent) - (row + 0.5).to(mx.dtype)
    sigma = 0.5 * (ca.index_select(0, ent) * dx * dx + cc.index_select(0, ent) * dy * dy)
    sigma = sigma + cb.index_select(0, ent) * dx * dy
    raw = op.index_select(0, ent) * torch.exp(-sigma)
    alpha = torch.where((raw >= ALPHA_MIN) & (sigma >= 0), raw.clamp_max(ALPHA_MAX), torch.zeros_like(raw))
    return dx, dy, alpha


def _rows(k: int, n: int, like: Tensor) -> Tensor:
    return torch.empty(k, n, dtype=like.dtype, device=like.device)


def forward_accumulate(cols: Tensor, ent: Tensor, counts: Tensor, T: Tensor, alpha: Tensor) -> Tensor:
    """Per-pixel sums [num_pixels, 5] of w * (r, g, b, z) and log(1 - alpha), w = T * alpha.

    Pairs are sorted by pixel, so the sums are segment sums (`counts` pairs per pixel), which is faster than a
    scatter. `cols` [4, M] holds the entries' r, g, b, z as rows: gathering 1-D rows is several times faster than
    gathering rows of an [M, 4] matrix.
    """
    w = T * alpha
    src = torch.empty(ent.shape[0], 5, dtype=T.dtype, device=T.device)  # filled in place instead of stacked
    for i in range(4):
        torch.mul(w, cols[i].index_select(0, ent), out=src[:, i])
    torch.log1p(-alpha, out=src[:, 4])
    return torch.segment_reduce(src, "sum", lengths=counts, axis=0)


def backward_pair_terms(cols: Tensor, grads: Tensor, ent: Tensor, pix: Tensor, T: Tensor, alpha: Tensor) -> Tensor:
    """s = w * dL/dw per pair, whose suffix sums carry the effect of each alpha on the pairs behind.

    `cols` [4, M] entry r, g, b, z; `grads` [5, num_pixels] dL/d(r, g, b, depth, T_final) per pixel.
    """
    v = grads[0].index_select(0, pix) * cols[0].index_select(0, ent)
    for i in range(1, 4):
        v = v + grads[i].index_select(0, pix) * cols[i].index_select(0, ent)
    return v


def backward_scatter(
    conic: Tensor,  # [3, M]
    op: Tensor,  # [M]
    grads: Tensor,  # [5, num_pixels]
    T_final: Tensor,
    ent: Tensor,
    pix: Tensor,
    dx: Tensor,
    dy: Tensor,
    alpha: Tensor,
    T: Tensor,
    v: Tensor,
    after: Tensor,
) -> Tensor:
    """Per-entry gradient sums [10, M]: d(mean2d) 2, d(conic) 3, d(opacity) 1, d(r, g, b) 3, d(depth) 1."""
    w = T * alpha
    tail = T_final.index_select(0, pix) * grads[4].index_select(0, pix)  # T_final acts like one more layer behind
    g_alpha = T * v - (after + tail) / (1.0 - alpha)
    # alpha = opacity * exp(-sigma) where it is neither clamped at 0.999 nor dropped below 1/255
    g_raw = torch.where((alpha > 0) & (alpha < ALPHA_MAX), g_alpha, torch.zeros_like(g_alpha))
    g_sigma = -g_raw * alpha
    a, b, c = (conic[i].index_select(0, ent) for i in range(3))
    src = _rows(10, ent.shape[0], T)
    torch.mul(g_sigma, a * dx + b * dy, out=src[0])
    torch.mul(g_sigma, b * dx + c * dy, out=src[1])
    torch.mul(g_sigma * dx, 0.5 * dx, out=src[2])
    torch.mul(g_sigma * dx, dy, out=src[3])
    torch.mul(g_sigma * dy, 0.5 * dy, out=src[4])
    torch.div(g_raw * alpha, op.index_select(0, ent), out=src[5])
    for i in range(4):
        torch.mul(w, grads[i].index_select(0, pix), out=src[6 + i])
    return torch.zeros(10, op.shape[0], dtype=T.dtype, device=T.device).index_add_(1, ent, src)


@dataclass(frozen=True)
class Kernels:
    """The per-pair stages, eager or compiled; the integer bookkeeping between them stays eager."""

    alpha: Callable[..., tuple[Tensor, Tensor, Tensor]] = pair_alpha
    accumulate: Callable[..., Tensor] = forward_accumulate
    backward_terms: Callable[..., Tensor] = backward_pair_terms
    scatter: Callable[..., Tensor] = backward_scatter

    @staticmethod
    def compiled() -> Kernels:
        c = functools.partial(torch.compile, dynamic=True)
        return Kernels(c(pair_alpha), c(forward_accumulate), c(backward_pair_terms), c(backward_scatter))


class _Composite(torch.autograd.Function):
    """Front-to-back compositing of (entry, pixel) pairs sorted by (pixel, depth) with early termination.

    Entries are Gaussians seen by one camera (means2d shifted by camera * height along y); outputs are per pixel of
    all cameras stacked: rgb sum [C*H*W, 3] (background not added), T_final [C*H*W], depth [C*H*W].
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        mx: Tensor,  # [M]
        my: Tensor,  # [M]
        ca: Tensor,  # [M] conic a
        cb: Tensor,  # [M] conic b
        cc: Tensor,  # [M] conic c
        op: Tensor,  # [M]
        colors: Tensor,  # [M, 3]
        depths: Tensor,  # [M]
        ent: Tensor,  # [P] sorted by (pixel, depth)
        pix: Tensor,  # [P]
        num_pixels: int,
        width: int,
        kernels: Kernels,
    ) -> tuple[Tensor, Tensor, Tensor]:
        dtype, dev = mx.dtype, mx.device
        ctx.kernels = kernels
        M = mx.shape[0]
        cols = torch.cat([colors.t(), depths[None]]).contiguous()  # [4, M]
        conic = torch.stack([ca, cb, cc])  # [3, M]
        if pix.numel() == 0:  # nothing drawn: keep the graph (means2d.grad becomes zeros, not None)
            ctx.empty = True
            ctx.M = M
            z = torch.zeros(num_pixels, dtype=dtype, device=dev)
            return torch.zeros(num_pixels, 3, dtype=dtype, device=dev), torch.ones_like(z), z
        ctx.empty = False
        dx, dy, alpha = kernels.alpha(mx, my, ca, cb, cc, op, ent, pix, width)  # [P]; alpha 0 = no contribution
        log1m = torch.log1p(-alpha).double()
        cs = torch.cumsum(log1m, 0)  # float64: a float32 running sum over all pairs would lose the digits
        counts = torch.bincount(pix, minlength=num_pixels)
        first = (torch.cumsum(counts, 0) - counts).clamp_max(pix.shape[0] - 1)
        excl = cs - log1m
        base = excl.index_select(0, first).index_select(0, pix)  # running sum before each pixel's segment
        # Early termination: a pair counts only while T after it stays > 1e-4; that is a prefix of every pixel's
        # segment (usually nearly all of it), so the rest is switched off rather than removed.
        alpha = torch.where((cs - base) > LOG_T_MIN, alpha, torch.zeros_like(alpha))
        T = torch.exp((excl - base).to(dtype))  # transmittance before each pair
        acc = kernels.accumulate(cols, ent, counts, T, alpha)  # [num_pixels, 5]
        T_final = torch.exp(acc[:, 4])
        ctx.save_for_backward(conic, op, cols, ent, pix, counts, dx, dy, alpha, T, T_final)
        return acc[:, :3], T_final, acc[:, 3]

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, g_rgb: Tensor, g_T: Tensor, g_depth: Tensor):  # type: ignore[override]
        nones = (None,) * 5
        if ctx.empty:
            z = g_T.new_zeros(ctx.M)
            return z, z, z, z, z, z, g_T.new_zeros(ctx.M, 3), z, *nones
        conic, op, cols, ent, pix, counts, dx, dy, alpha, T, T_final = ctx.saved_tensors
        k: Kernels = ctx.kernels
        grads = torch.cat([g_rgb.t(), g_depth[None], g_T[None]]).contiguous()  # [5, num_pixels]
        v = k.backward_terms(cols, grads, ent, pix, T, alpha)
        cs = torch.cumsum((T * alpha * v).double(), 0)
        last = (torch.cumsum(counts, 0) - 1).clamp_min(0)
        after = (cs.index_select(0, last).index_select(0, pix) - cs).to(T.dtype)  # sum of w * v over later pairs
        acc = k.scatter(conic, op, grads, T_final, ent, pix, dx, dy, alpha, T, v, after)
        g = acc.unbind(0)
        return (*g[:6], acc[6:9].t(), g[9], *nones)


def composite(
    means2d: Tensor,  # [M, 2]
    conics: Tensor,  # [M, 3]
    opacities: Tensor,  # [M]
    colors: Tensor,  # [M, 3]
    depths: Tensor,  # [M]
    cam: Tensor,  # [M]
    half: Tensor,  # [M, 2]
    num_cameras: int,
    width: int,
    height: int,
    kernels: Kernels,
    split_rows: bool = True,
) -> tuple[Tensor, Tensor, Tensor]:
    """Entries sorted by depth -> per-pixel (rgb sum [CHW, 3], T_final [CHW], depth [CHW]).

    A render whose screen boxes hold more pairs than `framework.splat.bands` allows is drawn in row bands (centres
    shifted up by the band's first row), so a 4096 x 4096 image needs memory for one band's pairs, not all of them."""
    bands = row_bands(means2d, half, width, height) if split_rows else [(0, height)]
    if len(bands) > 1:
        entries = (conics, opacities, colors, depths, cam, half, num_cameras, width)
        shift = means2d.new_tensor([0.0, 1.0])
        parts = [composite(means2d - r0 * shift, *entries, r1 - r0, kernels, False) for r0, r1 in bands]
        return tuple(
            torch.cat([p[i].reshape(num_cameras, -1, width, *p[i].shape[1:]) for p in parts], dim=1).flatten(0, 2)
            for i in range(3)
        )  # type: ignore[return-value]
    # Shift each entry's y by camera * height so row = pix // width addresses every camera's pixels.
    mx = means2d[:, 0].contiguous()
    my = (means2d[:, 1] + cam.to(means2d.dtype) * height).contiguous()
    ca, cb, cc = (x.contiguous() for x in conics.unbind(1))
    num_pixels = num_cameras * height * width
    with torch.no_grad():
        ent, pix = enumerate_pairs(means2d.detach(), conics.detach(), opacities.detach(), half, cam, width, height)
        pix, perm = torch.sort(pix, stable=True)  # stable: pairs were in depth order within each pixel
        ent = ent.index_select(0, perm)
    return _Composite.apply(mx, my, ca, cb, cc, opacities, colors, depths, ent, pix, num_pixels, width, kernels)


def sh_colors(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Colour = SH + 0.5, clamped at 0 from below: coeffs [M, K, 3], dirs [M, 3] (mean - camera centre)."""
    return (eval_sh(degree, coeffs, dirs) + 0.5).clamp_min(0.0)


@register("rasterizer", "torch_ref")
class TorchRefRasterizer(Rasterizer):
    """Pure-PyTorch rasterizer: any device, float32 or float64, differentiable in every Gaussian tensor."""

    def __init__(self, compile: bool = False) -> None:
        self.compile = compile
        self._kernels = Kernels.compiled() if compile else Kernels()

    def render(
        self,
        means: Tensor,
        quats: Tensor,
        scales: Tensor,
        opacities: Tensor,
        sh: Tensor,
        cameras: Cameras,
        *,
        sh_degree: int,
        background: Tensor | None = None,
        near: float = NEAR_PLANE,
        far: float = FAR_PLANE,
    ) -> RenderOutput:
        check_render_inputs(means, quats, scales, opacities, sh, sh_degree)
        if torch.is_autocast_enabled(means.device.type):
            # autocast would run the projection's products in half precision: the contract computes in float32
            with torch.autocast(means.device.type, enabled=False):
                return self.render(means, quats, scales, opacities, sh, cameras, sh_degree=sh_degree,
                                   background=background, near=near, far=far)  # fmt: skip
        if means.dtype in (torch.float16, torch.bfloat16):
            # Half precision cannot hold transmittances near 1e-4 or conics of small Gaussians: render in float32
            # and hand back the caller's dtype (gradients flow through the casts).
            out = self.render(
                *(t.float() for t in (means, quats, scales, opacities, sh)), cameras, sh_degree=sh_degree,
                background=None if background is None else background.float(), near=near, far=far,
            )  # fmt: skip
            half = means.dtype
            return RenderOutput(out.rgb.to(half), out.alpha.to(half), out.depth.to(half), out.means2d, out.radii)
        C, N, H, W = cameras.num, means.shape[0], cameras.height, cameras.width
        dtype, dev = means.dtype, means.device
        K = cameras.K.to(dev, dtype)
        w2c = cameras.world_to_cam.to(dev, dtype)
        proj = project_gaussians(means, quats, scales, opacities, K, w2c, W, H, near=near, far=far)
        means2d = proj.means2d  # [C, N, 2]
        if means2d.requires_grad:
            means2d.retain_grad()
        bg = torch.zeros(3, dtype=dtype, device=dev) if background is None else background.to(dev, dtype)

        with torch.no_grad():
            flat_valid = torch.nonzero(proj.valid.reshape(-1)).squeeze(1)  # [M] indices into C*N
            order = torch.argsort(proj.depths.detach().reshape(-1)[flat_valid], stable=True)
            flat = flat_valid[order]  # entries in depth order
            cam = torch.div(flat, N, rounding_mode="floor") if N > 0 else flat
            gid = flat - cam * N
        centers = cameras.centers().to(dev, dtype)  # [C, 3]
        colors = sh_colors(
            sh_degree, sh.index_select(0, gid), means.index_select(0, gid) - centers.index_select(0, cam)
        )
        rgb, T_final, depth = composite(
            means2d.reshape(-1, 2).index_select(0, flat),
            proj.conics.reshape(-1, 3).index_select(0, flat),
            opacities.index_select(0, gid),
            colors,
            proj.depths.reshape(-1).index_select(0, flat),
            cam,
            proj.half_extents.reshape(-1, 2).index_select(0, flat),
            C,
            W,
            H,
            self._kernels,
        )
        rgb = rgb + T_final[:, None] * bg
        return RenderOutput(
            rgb=rgb.reshape(C, H, W, 3),
            alpha=(1.0 - T_final).reshape(C, H, W, 1),
            depth=depth.reshape(C, H, W, 1),
            means2d=means2d,
            radii=proj.radii,
        )

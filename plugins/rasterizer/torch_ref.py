"""`torch_ref`: the pure-PyTorch rasterizer, the reference every other backend is compared with.

It works on the list of (Gaussian, pixel) pairs inside each projected footprint rather than on tiles: on a CPU the
padding and per-tile sorts of a tiled renderer cost far more than they save. Per frame:
1. enumerate, for every Gaussian (entries sorted by depth), the pixels of each box row that lie inside the ellipse
   where alpha can reach 1/255 (closed-form span per row, so almost no pair is wasted);
2. one stable integer sort by pixel puts the pairs in (pixel, depth) order;
3. composite every pixel with a segmented cumulative sum of log(1 - alpha) in float64 (a float32 running sum over
   millions of pairs would lose the per-pixel digits), which also gives the early-termination prefix;
4. per-pixel sums add the sorted pairs into their pixels in pair order (`index_add_` along the pixel axis).
A custom autograd function does the compositing backward in closed form from a second segmented sum (the effect of
each alpha on the pairs behind it), keeping per-pair indices, offsets, alpha, transmittance and the entry values the
forward gathered for each pair (conic, opacity, colour, depth), so the backward gathers only per-pixel gradients.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from framework.device_constants import constant_on
from framework.execution import COMPILED, Execution
from framework.interfaces.rasterizer import (
    ALPHA_MAX,
    ALPHA_MIN,
    FAR_PLANE,
    LOG_T_MIN,
    NEAR_PLANE,
    Rasterizer,
    check_render_inputs,
)
from framework.registry import register
from framework.splat.bands import row_bands
from framework.splat.pairs import depth_ordered_entries, enumerate_pairs, sort_pairs_by_pixel
from framework.splat.projection import Projection, project_gaussians
from framework.splat.sh import eval_sh
from framework.types import BlendWeights, Cameras, RenderOutput

# signs and halves that turn the scattered sums into the conic's six gradient terms (backward_scatter)
_CONIC_GRAD_SIGNS = torch.tensor([-1.0, -1.0, -0.5, -1.0, -0.5, -1.0])

_pixel_centre_cache: dict[tuple[int, int, torch.dtype, torch.device], tuple[Tensor, Tensor]] = {}


def pixel_centres(num_pixels: int, width: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """x and y of every flat pixel's centre, [num_pixels] each (rows run on across stacked cameras); cached.

    Looked up by the sorted pixel index, which reads them almost sequentially: cheaper than dividing every pair's
    pixel index (integer division does not vectorise; the float64 route costs six passes over the pairs)."""
    key = (num_pixels, width, dtype, device)
    if key not in _pixel_centre_cache:
        if len(_pixel_centre_cache) > 8:
            _pixel_centre_cache.clear()
        flat = torch.arange(num_pixels, device=device)
        row = torch.div(flat, width, rounding_mode="floor")
        _pixel_centre_cache[key] = ((flat - row * width).to(dtype) + 0.5, row.to(dtype) + 0.5)
    return _pixel_centre_cache[key]


def pair_alpha(
    mx: Tensor, my: Tensor, ca: Tensor, cb: Tensor, cc: Tensor, op: Tensor, ent: Tensor, px: Tensor, py: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Per pair (dx, dy, alpha) with d = mean2d - pixel centre and the contribution rule applied:
    alpha = min(0.999, opacity * exp(-sigma)), or 0 where that is below 1/255 or sigma < 0.

    Entry columns are [M] (means shifted by camera * height along y, so that the stacked pixel rows address every
    camera); `px`, `py` [P] are the pairs' pixel centres.
    """
    # In-place chains: every step is one pass over the pairs, with no temporaries to allocate. The constant factors
    # go on the [M] entry columns (-a/2, -c/2), so the pairs get -sigma in Horner form without a negation pass.
    # `torch.take` gathers a 1-D tensor 1.5-2.5x faster than `index_select` on CPU (random indices, 0.7-1.5M pairs).
    dx = torch.take(mx, ent).sub_(px)
    dy = torch.take(my, ent).sub_(py)
    neg_sigma = torch.take(ca * -0.5, ent).mul_(dx)  # -a dx / 2
    neg_sigma.sub_(torch.take(cb, ent).mul_(dy)).mul_(dx)  # (-a dx / 2 - b dy) dx
    neg_sigma.add_(torch.take(cc * -0.5, ent).mul_(dy).mul_(dy))  # - c dy^2 / 2
    raw = torch.take(op, ent).mul_(neg_sigma.exp())
    alpha = torch.where((raw >= ALPHA_MIN) & (neg_sigma <= 0), raw.clamp_max_(ALPHA_MAX), 0.0)
    return dx, dy, alpha


def pair_transmittance(alpha: Tensor, pix: Tensor, num_pixels: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Pairs sorted by (pixel, depth) -> (alpha with terminated pairs zeroed [P], log(1 - that alpha) [P], T before
    each pair [P], pairs per pixel [num_pixels]). The running sum of log(1 - alpha) is float64: a float32 sum over all
    pairs would lose the digits. Early termination: a pair counts only while T after it stays > 1e-4; that is a prefix
    of every pixel's segment (usually nearly all of it), so the rest is switched off rather than removed."""
    log1m = torch.log1p(-alpha)
    cs = torch.cumsum(log1m, 0, dtype=torch.float64)
    counts = torch.bincount(pix, minlength=num_pixels)
    first = (torch.cumsum(counts, 0) - counts).clamp_max(pix.shape[0] - 1)
    base = torch.take(torch.take(cs, first) - torch.take(log1m, first), pix)  # running sum before each pixel's segment
    through = cs.sub_(base)  # log T after each pair, within its pixel
    keep = through > LOG_T_MIN
    T = through.sub_(log1m).to(alpha.dtype).exp_()  # transmittance before each pair
    alpha = torch.where(keep, alpha, 0.0)
    log1m = torch.where(keep, log1m, 0.0)  # = log1p(-alpha) of the switched-off alpha
    return alpha, log1m, T, counts


def _rows(k: int, n: int, like: Tensor) -> Tensor:
    return torch.empty(k, n, dtype=like.dtype, device=like.device)


def forward_accumulate(
    pair_cols: Tensor, pix: Tensor, num_pixels: int, T: Tensor, alpha: Tensor, log1m: Tensor
) -> Tensor:
    """Per-pixel sums [5, num_pixels] of w * (r, g, b, z) and log(1 - alpha), w = T * alpha.

    `pair_cols` [4, P] holds each pair's entry r, g, b, z (gathered once, kept for the backward). The terms are
    contiguous rows added into the pixels' columns by `index_add_` along dim 1. With the pairs sorted by pixel that
    writes almost sequentially and sums in pair order, like a segment sum, at about half the cost of five
    `segment_reduce` calls.
    """
    acc = torch.zeros(5, num_pixels, dtype=T.dtype, device=T.device)
    acc[:4].index_add_(1, pix, torch.mul(pair_cols, T * alpha))
    acc[4:].index_add_(1, pix, log1m.unsqueeze(0))
    return acc


def backward_pair_terms(pair_cols: Tensor, pair_grads: Tensor) -> Tensor:
    """v = dL/dw per pair: the pixel's colour (and depth) gradients dotted with the pair's entry colour (and depth).

    `pair_cols` [K, P] the pairs' entry r, g, b (, z); `pair_grads` [K, P] the matching gradients of each pair's pixel.
    """
    v = pair_grads[0] * pair_cols[0]
    for i in range(1, pair_grads.shape[0]):
        v.addcmul_(pair_grads[i], pair_cols[i])
    return v


def backward_scatter(
    num_entries: int,
    pair_grads: Tensor,  # [K, P] dL/d(r, g, b (, depth)) of each pair's pixel
    tail: Tensor,  # [num_pixels] T_final * dL/dT_final
    ent: Tensor,
    pix: Tensor,
    dx: Tensor,
    dy: Tensor,
    alpha: Tensor,
    T: Tensor,
    w: Tensor,
    v: Tensor,
    after: Tensor,
) -> Tensor:
    """Per-entry sums [6 + K, M] of g_s dx, g_s dy, g_s dx^2 / 2, g_s dx dy, g_s dy^2 / 2, g_s and w dL/d(colour),
    with g_s = dL/dsigma. The entry's own conic and opacity turn them into d(mean2d), d(conic), d(opacity) (they are
    constant over its pairs, so they multiply the sums instead of every pair)."""
    behind = torch.take(tail, pix).add_(after).div_(1.0 - alpha)  # T_final acts like one more layer behind
    g_alpha = torch.mul(T, v).sub_(behind)
    K = pair_grads.shape[0]
    src = _rows(6 + K, ent.shape[0], T)
    # alpha = opacity * exp(-sigma), so dL/dsigma = -alpha dL/dalpha: zero where alpha was dropped (alpha = 0 already
    # gives it) or clamped at 0.999. The pair rows hold -g_s, and dx^2, dy^2 without their 1/2: the signs and halves
    # are applied to the [6, M] entry sums, not to every pair.
    neg_g_sigma = torch.mul(g_alpha, alpha, out=src[5]).masked_fill_(alpha >= ALPHA_MAX, 0.0)
    g_sx = torch.mul(neg_g_sigma, dx, out=src[0])
    g_sy = torch.mul(neg_g_sigma, dy, out=src[1])
    torch.mul(g_sx, dx, out=src[2])
    torch.mul(g_sx, dy, out=src[3])
    torch.mul(g_sy, dy, out=src[4])
    for i in range(K):
        torch.mul(w, pair_grads[i], out=src[6 + i])
    acc = torch.zeros(6 + K, num_entries, dtype=T.dtype, device=T.device).index_add_(1, ent, src)
    acc[:6] *= constant_on(_CONIC_GRAD_SIGNS, acc.device, acc.dtype)[:, None]
    return acc


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
    ) -> tuple[Tensor, Tensor, Tensor]:
        dtype, dev = mx.dtype, mx.device
        M = mx.shape[0]
        ctx.M = M
        if pix.numel() == 0:  # nothing drawn: keep the graph (means2d.grad becomes zeros, not None)
            ctx.empty = True
            z = torch.zeros(num_pixels, dtype=dtype, device=dev)
            return torch.zeros(num_pixels, 3, dtype=dtype, device=dev), torch.ones_like(z), z
        ctx.empty = False
        px, py = pixel_centres(num_pixels, width, dtype, dev)
        px, py = torch.take(px, pix), torch.take(py, pix)
        dx, dy, alpha = pair_alpha(mx, my, ca, cb, cc, op, ent, px, py)  # [P]; alpha 0 = no contribution
        alpha, log1m, T, counts = pair_transmittance(alpha, pix, num_pixels)
        pair_cols = _rows(4, ent.shape[0], colors)  # [4, P]: each pair's entry r, g, b, z
        for i, col in enumerate((*colors.unbind(1), depths)):
            torch.take(col, ent, out=pair_cols[i])
        acc = forward_accumulate(pair_cols, pix, num_pixels, T, alpha, log1m)  # [5, num_pixels]
        T_final = torch.exp(acc[4])
        ctx.save_for_backward(ca, cb, cc, op, pair_cols, ent, pix, counts, dx, dy, alpha, T, T_final)
        ctx.set_materialize_grads(False)  # an unused output (depth, usually) gets no backward work
        return acc[:3].t().contiguous(), T_final, acc[3]

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, g_rgb: Tensor | None, g_T: Tensor | None, g_depth: Tensor | None):  # type: ignore[override]
        nones = (None,) * 4
        M = ctx.M
        given = [g for g in (g_rgb, g_T, g_depth) if g is not None]
        if not given:
            return (None,) * 8 + nones
        if ctx.empty:
            z = given[0].new_zeros(M)
            return z, z, z, z, z, z, given[0].new_zeros(M, 3), z, *nones
        ca, cb, cc, op, pair_cols, ent, pix, counts, dx, dy, alpha, T, T_final = ctx.saved_tensors
        num_pixels = T_final.shape[0]
        if g_rgb is None:
            g_rgb = T_final.new_zeros(num_pixels, 3)
        rows = [g_rgb.t()] if g_depth is None else [g_rgb.t(), g_depth[None]]
        grads = torch.cat(rows).contiguous()  # [K, num_pixels], K = 3 or 4 (with depth)
        K = grads.shape[0]
        tail = T_final * g_T if g_T is not None else torch.zeros_like(T_final)
        pair_grads = _rows(K, pix.shape[0], grads)  # [K, P] gathered once for both kernels
        for i in range(K):
            torch.take(grads[i], pix, out=pair_grads[i])
        v = backward_pair_terms(pair_cols[:K], pair_grads)
        w = T * alpha
        cs = torch.cumsum(w * v, 0, dtype=torch.float64)
        last = (torch.cumsum(counts, 0) - 1).clamp_min(0)
        after = torch.take(torch.take(cs, last), pix).sub_(cs).to(T.dtype)  # sum of w * v over later pairs
        acc = backward_scatter(M, pair_grads, tail, ent, pix, dx, dy, alpha, T, w, v, after)  # [6 + K, M]
        s_x, s_y, s_xx, s_xy, s_yy, s_g = acc[:6]
        g_mx, g_my = ca * s_x + cb * s_y, cb * s_x + cc * s_y  # d sigma / d mean2d = (a dx + b dy, b dx + c dy)
        g_op = -s_g / op  # d alpha / d opacity = alpha / opacity, and s_g sums -alpha dL/dalpha
        g_depth_out = acc[9] if K == 4 else torch.zeros_like(g_op)
        return g_mx, g_my, s_xx, s_xy, s_yy, g_op, acc[6:9].t(), g_depth_out, *nones


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
    split_rows: bool = True,
) -> tuple[Tensor, Tensor, Tensor]:
    """Entries sorted by depth -> per-pixel (rgb sum [CHW, 3], T_final [CHW], depth [CHW]).

    A render whose screen boxes hold more pairs than `framework.splat.bands` allows is drawn in row bands (centres
    shifted up by the band's first row), so a 4096 x 4096 image needs memory for one band's pairs, not all of them."""
    bands = row_bands(means2d, half, width, height) if split_rows else [(0, height)]
    if len(bands) > 1:
        entries = (conics, opacities, colors, depths, cam, half, num_cameras, width)
        shift = means2d.new_tensor([0.0, 1.0])
        parts = [composite(means2d - r0 * shift, *entries, r1 - r0, False) for r0, r1 in bands]
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
        ent, pix = sort_pairs_by_pixel(ent, pix, num_pixels)
    return _Composite.apply(mx, my, ca, cb, cc, opacities, colors, depths, ent, pix, num_pixels, width)


def sh_colors(degree: int, coeffs: Tensor, dirs: Tensor, execution: Execution = COMPILED) -> Tensor:
    """Colour = SH + 0.5, clamped at 0 from below: coeffs [M, K, 3], dirs [M, 3] (mean - camera centre)."""
    return (eval_sh(degree, coeffs, dirs, execution) + 0.5).clamp_min(0.0)


@register("rasterizer", "torch_ref")
class TorchRefRasterizer(Rasterizer):
    """Pure-PyTorch rasterizer: any device, float32 or float64, differentiable in every Gaussian tensor."""

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
                return self.render(
                    means,
                    quats,
                    scales,
                    opacities,
                    sh,
                    cameras,
                    sh_degree=sh_degree,
                    background=background,
                    near=near,
                    far=far,
                )
        if means.dtype in (torch.float16, torch.bfloat16):
            # Half precision cannot hold transmittances near 1e-4 or conics of small Gaussians: render in float32
            # and hand back the caller's dtype (gradients flow through the casts).
            out = self.render(
                *(t.float() for t in (means, quats, scales, opacities, sh)),
                cameras,
                sh_degree=sh_degree,
                background=None if background is None else background.float(),
                near=near,
                far=far,
            )
            half = means.dtype
            return RenderOutput(out.rgb.to(half), out.alpha.to(half), out.depth.to(half), out.means2d, out.radii)
        C, H, W = cameras.num, cameras.height, cameras.width
        dtype, dev = means.dtype, means.device
        K = cameras.K.to(dev, dtype)
        w2c = cameras.world_to_cam.to(dev, dtype)
        proj = self.project(means, quats, scales, opacities, K, w2c, W, H, near, far)
        means2d = proj.means2d  # [C, N, 2]
        if means2d.requires_grad:
            means2d.retain_grad()
        bg = torch.zeros(3, dtype=dtype, device=dev) if background is None else background.to(dev, dtype)

        with torch.no_grad():
            flat, cam, gid = depth_ordered_entries(proj.valid, proj.depths)  # [M] each: entries in depth order
        centers = cameras.centers().to(dev, dtype)  # [C, 3]
        if 2 * flat.numel() >= C * means.shape[0]:
            # most (camera, Gaussian) entries are visible: evaluate the SH of every one and gather [M, 3] colours,
            # rather than gathering [M, K, 3] coefficients (and scattering their gradient back)
            dirs = means[None] - centers[:, None]  # [C, N, 3]
            colors = sh_colors(sh_degree, sh, dirs, self.execution).reshape(-1, 3).index_select(0, flat)
        else:
            dirs = means.index_select(0, gid) - centers.index_select(0, cam)  # [M, 3]
            colors = sh_colors(sh_degree, sh.index_select(0, gid), dirs, self.execution)
        rgb, T_final, depth = self.composite_entries(
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
        )
        rgb = rgb + T_final[:, None] * bg
        return RenderOutput(
            rgb=rgb.reshape(C, H, W, 3),
            alpha=(1.0 - T_final).reshape(C, H, W, 1),
            depth=depth.reshape(C, H, W, 1),
            means2d=means2d,
            radii=proj.radii,
        )

    def project(
        self,
        means: Tensor,  # [N, 3]
        quats: Tensor,  # [N, 4]
        scales: Tensor,  # [N, 3]
        opacities: Tensor,  # [N]
        K: Tensor,  # [C, 3, 3]
        world_to_cam: Tensor,  # [C, 4, 4]
        width: int,
        height: int,
        near: float,
        far: float,
    ) -> Projection:
        """The EWA projection (`framework.splat.projection`), differentiable; a subclass may replace it (`numba`)."""
        return project_gaussians(
            means,
            quats,
            scales,
            opacities,
            K,
            world_to_cam,
            width,
            height,
            near=near,
            far=far,
            execution=self.execution,
        )

    def composite_entries(
        self,
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
    ) -> tuple[Tensor, Tensor, Tensor]:
        """The depth-ordered entries -> per pixel of the stacked cameras (rgb sum [CHW, 3], T_final [CHW], depth
        [CHW]), differentiable; a subclass may replace it (`numba` does, with compiled loops on the CPU)."""
        return composite(means2d, conics, opacities, colors, depths, cam, half, num_cameras, width, height)

    @torch.no_grad()
    def blend_weights(
        self,
        means: Tensor,
        quats: Tensor,
        scales: Tensor,
        opacities: Tensor,
        cameras: Cameras,
        *,
        near: float = NEAR_PLANE,
        far: float = FAR_PLANE,
    ) -> BlendWeights:
        """Per Gaussian, the largest blending weight T * alpha at any pixel of any camera, the sum of their squares and
        the number of pairs with one (pruning).

        The same pairs, alphas and early termination as `render`, with no colours, no autograd and reductions in place
        of the colour sums, so it is a separate pass that the training step never runs."""
        C, N, H, W = cameras.num, means.shape[0], cameras.height, cameras.width
        dtype, dev = means.dtype, means.device
        out = BlendWeights.zeros(N, dev, dtype)
        proj = project_gaussians(
            means,
            quats,
            scales,
            opacities,
            cameras.K.to(dev, dtype),
            cameras.world_to_cam.to(dev, dtype),
            W,
            H,
            near=near,
            far=far,
            execution=self.execution,
        )
        flat, cam, gid = depth_ordered_entries(proj.valid, proj.depths)  # [M] each
        if flat.numel() == 0:
            return out
        means2d = proj.means2d.reshape(-1, 2).index_select(0, flat)
        conics = proj.conics.reshape(-1, 3).index_select(0, flat)
        op = opacities.index_select(0, gid)
        ent, pix = enumerate_pairs(
            means2d, conics, op, proj.half_extents.reshape(-1, 2).index_select(0, flat), cam, W, H
        )
        if pix.numel() == 0:
            return out
        ent, pix = sort_pairs_by_pixel(ent, pix, C * H * W)
        my = means2d[:, 1] + cam.to(dtype) * H
        px, py = pixel_centres(C * H * W, W, dtype, dev)
        _, _, alpha = pair_alpha(
            means2d[:, 0], my, *conics.unbind(1), op, ent, torch.take(px, pix), torch.take(py, pix)
        )
        alpha, _, T, _ = pair_transmittance(alpha, pix, C * H * W)
        w = (T * alpha).double()  # [P] 0 where the pair does not contribute
        g = torch.take(gid, ent)  # [P]
        out.max.scatter_reduce_(0, g, w.to(out.max.dtype), reduce="amax")
        out.square_sum.index_add_(0, g, w * w)
        out.pairs.index_add_(0, g, (w > 0).double())
        return out

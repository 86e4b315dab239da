"""The (Gaussian, pixel) pairs a splatting compositor visits: which entries are visible in depth order, which pixels
each can reach, and the pairs sorted by pixel with depth order kept inside each pixel.

Shared by the torch_ref and jax rasterizers (and torch_ref's pruning pass), so the backends agree on which pairs
exist; each applies the exact alpha test itself. Torch only, no gradients: the pair list is an index structure.
"""

from __future__ import annotations

import torch
from torch import Tensor

from framework.splat.contract import ALPHA_MIN, BOX_MARGIN


def _to_index(x: Tensor, lo: int, hi: int) -> Tensor:
    """Clamp in floating point first: a huge or infinite coordinate would overflow the integer conversion."""
    return x.clamp(lo, hi).long()


def depth_ordered_entries(valid: Tensor, depths: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """valid [C, N] bool, depths [C, N] -> the visible (camera, Gaussian) entries in depth order: flat index into C*N
    [M], camera [M], Gaussian [M]. Stable, so equal depths keep the Gaussians' order (as every backend must)."""
    N = depths.shape[1]
    flat_valid = torch.nonzero(valid.reshape(-1)).squeeze(1)  # [M]
    flat = flat_valid[torch.argsort(depths.detach().reshape(-1)[flat_valid], stable=True)]
    cam = torch.div(flat, N, rounding_mode="floor") if N > 0 else flat
    return flat, cam, flat - cam * N


def enumerate_pairs(
    means2d: Tensor,  # [M, 2] (detached, unshifted)
    conics: Tensor,  # [M, 3] (detached)
    opacities: Tensor,  # [M] (detached)
    half: Tensor,  # [M, 2] box half extents in pixels
    cam: Tensor,  # [M] camera index of each entry
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """Every (entry, pixel) pair whose pixel centre may have alpha >= 1/255 -> (entry [P], flat pixel [P] into C*H*W).

    Rows come from the screen box; within a row the pixels come from the exact span of the ellipse
    sigma <= ln(255 * opacity) (widened by BOX_MARGIN), so hardly any enumerated pair is wasted and none that can
    contribute is missed. Pairs come out entry-major, so entries given in depth order give pairs in depth order.
    """
    dev = means2d.device
    M = means2d.shape[0]
    y0 = _to_index(torch.ceil(means2d[:, 1] - half[:, 1] - BOX_MARGIN - 0.5), 0, height)
    y1 = _to_index(torch.floor(means2d[:, 1] + half[:, 1] + BOX_MARGIN - 0.5), -1, height - 1)
    nrows = (y1 - y0 + 1).clamp_min(0)  # [M]
    R = int(nrows.sum())
    r_ent = torch.repeat_interleave(torch.arange(M, device=dev), nrows, output_size=R)  # [R]
    r_y = torch.take(y0, r_ent) + torch.arange(R, device=dev) - torch.take(torch.cumsum(nrows, 0) - nrows, r_ent)
    dy = torch.take(means2d[:, 1], r_ent) - (r_y.to(means2d.dtype) + 0.5)
    a, b, c = (torch.take(conics[:, i], r_ent) for i in range(3))
    L = torch.log((torch.take(opacities, r_ent) / ALPHA_MIN).clamp_min(1.0))
    disc = (b * dy) ** 2 - a * (c * dy * dy - 2.0 * L)  # sigma(dx) <= L is a quadratic in dx
    sq = torch.sqrt(disc.clamp_min(0.0))
    a_safe = a.clamp_min(torch.finfo(a.dtype).tiny)
    mx = torch.take(means2d[:, 0], r_ent)
    x0 = _to_index(torch.ceil(mx - (-b * dy + sq) / a_safe - BOX_MARGIN - 0.5), 0, width)
    x1 = _to_index(torch.floor(mx - (-b * dy - sq) / a_safe + BOX_MARGIN - 0.5), -1, width - 1)
    n = torch.where(disc >= 0, (x1 - x0 + 1).clamp_min(0), torch.zeros_like(x0))  # [R]
    P = int(n.sum())
    p_row = torch.repeat_interleave(torch.arange(R, device=dev), n, output_size=P)  # [P]
    row_base = (torch.take(cam, r_ent) * height + r_y) * width + x0 - (torch.cumsum(n, 0) - n)  # [R]
    pix = torch.take(row_base, p_row) + torch.arange(P, device=dev)
    ent = torch.take(r_ent, p_row)
    return ent, pix


def sort_pairs_by_pixel(ent: Tensor, pix: Tensor, num_pixels: int) -> tuple[Tensor, Tensor]:
    """(entry [P], pixel [P]) -> the same pairs sorted by pixel, depth order kept within each pixel (stable sort).

    The CPU sort's cost follows the key width, so the keys are the narrowest integers that hold every pixel index
    (each halving of the width about halves the sort); the returned indices stay int64 (int32 index tensors made
    torch's gathers slower)."""
    shift = 2**15 if num_pixels <= 2**16 else 0
    key_dtype = torch.int16 if shift else torch.int32 if num_pixels <= 2**31 else torch.int64
    keys, perm = torch.sort((pix - shift).to(key_dtype), stable=True)
    return torch.take(ent, perm), keys.long().add_(shift)

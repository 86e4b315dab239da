"""SSIM's separable Gaussian filter with reflected borders as a compiled loop (numba), and its adjoint: the filter
of `framework.kernels.ssim`.

Why: the D-SSIM term filters five moment maps of the render (`framework.image.ssim.ssim_map`) with an 11-tap window
along each axis. Through `kornia.filters.filter2d_separable` that is a reflection pad and a depthwise convolution per
axis, whose backward dominates a CPU training step's D-SSIM. The arithmetic is 22 multiply-adds per pixel and plane
each way. Here each axis is one loop over whole rows that the compiler vectorises, and the border columns and rows
index the mirror directly.

Same definition as kornia's: correlation along W first, then along H, each with torch's 'reflect' border (mirrored
about the edge pixel, which is not repeated: index -1 reads 1). The backward is the exact adjoint: the same taps
scattered to where the forward read them, reflected reads included, so it also holds for an asymmetric kernel. Sums
run in the planes' dtype, tap by tap; they agree with kornia's to rounding (`tests/test_compiled_filter.py` compares
values in float64 with scipy's and the adjoint with kornia's gradients).
"""

from __future__ import annotations

from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _mirror(i, n):
    """torch's 'reflect' index of i on an axis of n samples, for -n < i < 2n - 1."""
    if i < 0:
        return -i
    if i >= n:
        return 2 * (n - 1) - i
    return i


@njit(cache=True, nogil=True)
def _correlate_rows(src, taps, adjoint, out) -> None:
    """out [W] = the reflect-bordered correlation of src [W] with taps [K] (adjoint: its transpose, scattered);
    out is overwritten."""
    W, K = src.shape[0], taps.shape[0]
    r = (K - 1) // 2
    out[:] = 0.0
    for k in range(K):
        g, off = taps[k], k - r
        lo, hi = max(0, -off), min(W, W - off)  # j + off inside [0, W) for lo <= j < hi
        # the interior through slices: an index j + off that may be negative makes numba check for wraparound,
        # which keeps the loop scalar (7x slower here)
        shifted, aligned = (out, src) if adjoint else (src, out)
        shifted_in, aligned_in = shifted[lo + off : hi + off], aligned[lo:hi]
        if adjoint:
            for j in range(hi - lo):
                shifted_in[j] += g * aligned_in[j]
            for j in range(0, lo):
                out[_mirror(j + off, W)] += g * src[j]
            for j in range(hi, W):
                out[_mirror(j + off, W)] += g * src[j]
        else:
            for j in range(hi - lo):
                aligned_in[j] += g * shifted_in[j]
            for j in range(0, lo):
                out[j] += g * src[_mirror(j + off, W)]
            for j in range(hi, W):
                out[j] += g * src[_mirror(j + off, W)]


@njit(cache=True, nogil=True)
def _correlate_columns(src, taps, adjoint, out) -> None:
    """out [H, W] = the reflect-bordered correlation of src [H, W] along H with taps [K] (adjoint: its transpose),
    whole rows at a time; out is overwritten."""
    H, K = src.shape[0], taps.shape[0]
    r = (K - 1) // 2
    out[:, :] = 0.0
    W = src.shape[1]
    for i in range(H):
        for k in range(K):
            g, m = taps[k], _mirror(i + k - r, H)
            if adjoint:
                for j in range(W):
                    out[m, j] += g * src[i, j]
            else:
                for j in range(W):
                    out[i, j] += g * src[m, j]


@njit(cache=True, nogil=True)
def filter_planes(src, taps_x, taps_y, adjoint, start, stop, work, out) -> None:
    """Planes start..stop of src [P, H, W] -> out [P, H, W]: along W with taps_x, then along H with taps_y (adjoint:
    the transpose, H first); work [P, H, W] holds the intermediate."""
    for p in range(start, stop):
        if adjoint:
            _correlate_columns(src[p], taps_y, True, work[p])
            for i in range(src.shape[1]):
                _correlate_rows(work[p, i], taps_x, True, out[p, i])
        else:
            for i in range(src.shape[1]):
                _correlate_rows(src[p, i], taps_x, False, work[p, i])
            _correlate_columns(work[p], taps_y, False, out[p])

"""Differentiable front-to-back compositing as compiled loops: the training step's compositor on the CPU.

Why: `torch_ref`'s compositor lists every (entry, pixel) pair, sorts them by pixel and runs a dozen passes over the
pair arrays forward and as many backward, each a separate tensor operation with its own memory traffic. The compiled
loops of `framework.kernels.rasterize` visit the pairs once forward (`accumulate`, which skips finished pixels and
logs the pairs it added: slot, position, alpha) and replay that log backwards (`accumulate_backward`), so the
backward touches only the pairs that contributed, and per pixel walks its transmittance back from the final one.
Everything runs in float64 inside, so float32 renders and gradients are at least as accurate as `torch_ref`'s float32
ones. A whole training render, forward and backward, takes under half of torch_ref's time (docs/results/speed.md).

The colours stay in PyTorch and the projection has its own Function (`framework.kernels.projection`); autograd
carries the gradients between them, and densification reads `means2d.grad` as before.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from framework.kernels import rasterize
from framework.kernels.rasterize import float64_array

_capacity_hint = [0]  # room for the pair log: the last render's count, plus a quarter


class CompiledComposite(torch.autograd.Function):
    """Entries in depth order (all cameras stacked, `cam` naming each one's camera) -> per pixel of the stacked
    images: rgb sum [C*H*W, 3] (background not added), T_final [C*H*W], depth [C*H*W]; the contract of `torch_ref`'s
    compositor (`plugins.rasterizer.torch_ref.composite`)."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        means2d: Tensor,  # [M, 2]
        conics: Tensor,  # [M, 3]
        opacities: Tensor,  # [M]
        colors: Tensor,  # [M, 3]
        depths: Tensor,  # [M]
        half: Tensor,  # [M, 2] screen-box half extents (no gradient)
        cam: Tensor,  # [M] camera of each entry
        num_cameras: int,
        width: int,
        height: int,
    ) -> tuple[Tensor, Tensor, Tensor]:
        M, dtype = means2d.shape[0], means2d.dtype
        if num_cameras * height * (width + 1) >= 2**31 or M >= 2**31:
            raise ValueError(
                f"compiled compositing: {num_cameras} x {height} x {width} pixels and {M} entries exceed "
                "the pair log's 32-bit indices; render fewer cameras at once or use rasterizer=torch_ref"
            )
        entries = tuple(float64_array(t) for t in (means2d, conics, opacities, colors, depths, half))
        order = np.arange(M)
        base_row = cam.to(torch.int64).numpy() * height  # [M] first stacked row of each entry's image
        slots = num_cameras * height * (width + 1)  # one per pixel, and a row-end marker per row
        # no gradient asked (a half-precision render, say): no pair log to keep
        capacity = max(_capacity_hint[0], 8 * M) if any(ctx.needs_input_grad[:5]) else 0
        while True:
            T = np.ones(slots)
            acc = np.zeros((slots, 4))  # [slots, 4] sums of T * alpha * (r, g, b, z)
            log = (np.empty(capacity, dtype=np.int32), np.empty(capacity, dtype=np.int32), np.empty(capacity))
            count = rasterize.accumulate(order, base_row, *entries, width, height, T, acc, *log)
            if count <= capacity or capacity == 0:
                break
            capacity = count + count // 4  # rare: the first render, or a jump in the number of pairs
        if capacity:
            _capacity_hint[0] = count + count // 4
        log = tuple(a[:count] for a in log)  # [P] the pairs added, in order
        ctx.entries, ctx.order, ctx.base_row, ctx.T, ctx.log = entries[:5], order, base_row, T, log
        ctx.shape = (num_cameras * height, width)
        ctx.set_materialize_grads(False)  # an unused output (depth, usually) gets no backward work

        pixels = num_cameras * height * width
        out_dtype = np.float32 if dtype == torch.float32 else np.float64  # sums in float64, stored as the caller's
        rgb, trans, depth = np.empty((pixels, 3), out_dtype), np.empty(pixels, out_dtype), np.empty(pixels, out_dtype)
        rasterize.slots_to_pixels(acc, T, width, np.zeros(3), rgb, trans, depth, False)  # background added later
        return tuple(torch.from_numpy(a).to(dtype) for a in (rgb, trans, depth))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, g_rgb: Tensor | None, g_T: Tensor | None, g_depth: Tensor | None):  # type: ignore[override]
        means2d, conics, opacities, colors, depths = ctx.entries
        width = ctx.shape[1]
        M = means2d.shape[0]
        like = next(g for g in (g_rgb, g_T, g_depth) if g is not None)

        def pixels(g: Tensor | None, k: int) -> np.ndarray:  # [C*H*W, k] float64 (size 0: no gradient)
            return float64_array(g).reshape(-1, k) if g is not None else np.empty((0, k))

        T = ctx.T.copy()  # walked back to 1 by the backward
        g_acc, tail = np.empty((T.shape[0], 4)), np.empty(T.shape[0])  # [slots, 4], [slots]: T_final * dL/dT_final
        rasterize.pixels_to_slots(
            pixels(g_rgb, 3), pixels(g_T, 1)[:, 0], pixels(g_depth, 1)[:, 0], T, width, g_acc, tail
        )
        grads = (np.zeros((M, 2)), np.zeros((M, 3)), np.zeros(M), np.zeros((M, 3)), np.zeros(M))
        rasterize.accumulate_backward(
            ctx.order, ctx.base_row, means2d, conics, opacities, colors, depths, width, T, *ctx.log, g_acc, tail, *grads
        )
        out = tuple(torch.from_numpy(g).to(like.dtype) for g in grads)
        return (*out, None, None, None, None, None)

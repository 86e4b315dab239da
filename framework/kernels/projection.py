"""Differentiable EWA projection as compiled loops: the training step's projection on the CPU.

Why: `framework.splat.projection.project_gaussians` is about 300 small tensor operations forward and as many
backward, each a few microseconds of overhead however few Gaussians there are. The compiled forward
(`framework.kernels.rasterize.project`) and its hand-written backward (`project_backward`, which recomputes each
entry's forward and applies the chain rule in reverse) do the same arithmetic per entry in float64 without that
overhead. The rules (culling, the field-of-view clamp, the dilation, the screen box) are the projection's, and
`tests/test_numba_rasterizer.py` checks the gradients against autograd through `project_gaussians` in float64.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from framework.kernels import rasterize
from framework.kernels.rasterize import float64_array
from framework.splat.contract import EPS2D
from framework.splat.projection import Projection


class _CompiledProjection(torch.autograd.Function):
    """(means [N, 3], quats [N, 4], scales [N, 3]) -> means2d [C, N, 2], conics [C, N, 3], depths [C, N], each
    differentiable; the culling and box outputs are returned as constants."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        means: Tensor,
        quats: Tensor,
        scales: Tensor,
        opacities: Tensor,
        K: Tensor,
        world_to_cam: Tensor,
        width: int,
        height: int,
        near: float,
        far: float,
    ) -> tuple[Tensor, ...]:
        C, N, dtype = K.shape[0], means.shape[0], means.dtype
        inputs = tuple(float64_array(t) for t in (means, quats, scales, K, world_to_cam))
        means2d, conics, depths = np.empty((C, N, 2)), np.empty((C, N, 3)), np.empty((C, N))
        half, cov2d = np.empty((C, N, 2)), np.empty((C, N, 3))
        radii, valid = np.empty((C, N), dtype=np.int32), np.empty((C, N), dtype=np.bool_)
        m, q, s, k, w2c = inputs
        rasterize.project(
            m,
            q,
            s,
            float64_array(opacities),
            k,
            w2c,
            width,
            height,
            float(near),
            float(far),
            EPS2D,
            means2d,
            conics,
            depths,
            half,
            radii,
            valid,
            cov2d,
        )
        ctx.inputs, ctx.valid, ctx.size = inputs, valid, (width, height)
        ctx.set_materialize_grads(False)
        out = [torch.from_numpy(a).to(dtype) for a in (means2d, conics, depths, half, cov2d)]
        out += [torch.from_numpy(radii), torch.from_numpy(valid)]
        ctx.mark_non_differentiable(*out[3:])
        return tuple(out)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, g_means2d: Tensor | None, g_conics: Tensor | None, g_depths: Tensor | None, *_):  # type: ignore[override]
        m, q, s, k, w2c = ctx.inputs
        C, N = ctx.valid.shape
        like = next(g for g in (g_means2d, g_conics, g_depths) if g is not None)

        def given(g: Tensor | None, shape: tuple[int, ...]) -> np.ndarray:
            return np.zeros(shape) if g is None else float64_array(g)

        grads = (np.zeros((N, 3)), np.zeros((N, 4)), np.zeros((N, 3)))
        rasterize.project_backward(
            m,
            q,
            s,
            k,
            w2c,
            *ctx.size,
            EPS2D,
            ctx.valid,
            given(g_means2d, (C, N, 2)),
            given(g_conics, (C, N, 3)),
            given(g_depths, (C, N)),
            *grads,
        )
        g_means, g_quats, g_scales = (torch.from_numpy(g).to(like.dtype) for g in grads)
        return g_means, g_quats, g_scales, None, None, None, None, None, None, None


def project_compiled(
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
    """`project_gaussians`' result as compiled loops, differentiable in means, quats and scales (not in the cameras,
    which no training step optimises, nor in the 2D covariance, which the render does not read: both are constants)."""
    means2d, conics, depths, half, cov2d, radii, valid = _CompiledProjection.apply(
        means, quats, scales, opacities, K, world_to_cam, width, height, near, far
    )
    return Projection(
        means2d=means2d, conics=conics, cov2d=cov2d, depths=depths, half_extents=half, radii=radii, valid=valid
    )

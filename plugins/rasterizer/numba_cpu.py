"""`numba`: `torch_ref`'s function on the CPU as compiled loops; the CPU default for training and rendering.

It renders compiled wherever the model's execution (`framework.execution`) compiles its tensors (CPU float32/float64
under the compiled kernels, the default on a CPU); under the torch execution, or on another device, it is `torch_ref`.

Viewing, evaluation, frame-rate timing and the novel-view and novel-pose frames of a trained avatar render without
gradients: there projection, SH colours and compositing all run compiled. At the sizes a CPU renders in real time,
the eager rasterizer's time is mostly per-operation overhead (`framework.kernels.rasterize` says why and how the
loops avoid it). A render whose inputs require gradients (training) runs `torch_ref`'s render with two steps replaced
by compiled loops with hand-written backward passes: the projection (`framework.kernels.projection`) and the
compositing (`framework.kernels.compositing`). There the rasterizer's SH colours keep torch_ref's autograd code
(an avatar hands it degree 0: its view colour is compiled with its backward, `framework.kernels.sh_colours`), and
means2d is still an autograd tensor, so densification's `means2d.grad` is filled as before. Pruning's blending
weights are `torch_ref`'s. Inputs on another device run `torch_ref` itself; half-precision inputs are rendered in
float32, as `torch_ref` does, through the same compiled steps.

Under the same execution an avatar also poses its Gaussians with compiled loops when it needs no gradients
(`framework.kernels.skinning`, for LBS deformers with baked weights) and evaluates each Gaussian's colour towards the
camera compiled (`framework.kernels.sh_colours`), so with this backend the whole CPU frame but F_a (oneDNN's fused
layers) and the bone transforms runs compiled.

The first render on a machine compiles the loops (seconds for the rasterizer, the skinning and the backward passes).
numba caches them in `__pycache__`, and a later process loads them in about a second, numba's import included.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from framework.execution import Execution
from framework.interfaces.rasterizer import EPS2D, FAR_PLANE, NEAR_PLANE, Rasterizer, check_render_inputs
from framework.registry import register
from framework.splat.projection import Projection
from framework.types import BlendWeights, Cameras, RenderOutput
from plugins.rasterizer.torch_ref import TorchRefRasterizer


class _CompiledTraining(TorchRefRasterizer):
    """torch_ref's differentiable render with its projection and compositing compiled where the execution compiles
    them (CPU float32 and float64); other devices and dtypes keep torch_ref's own steps."""

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
        if not self.execution.compiled(means) or K.requires_grad or world_to_cam.requires_grad:
            return super().project(means, quats, scales, opacities, K, world_to_cam, width, height, near, far)
        from framework.kernels.projection import project_compiled  # lazy: numba's import (module docstring)

        return project_compiled(means, quats, scales, opacities, K, world_to_cam, width, height, near, far)

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
        if not self.execution.compiled(means2d):
            return super().composite_entries(
                means2d, conics, opacities, colors, depths, cam, half, num_cameras, width, height
            )
        from framework.kernels.compositing import CompiledComposite  # lazy: numba's import (module docstring)

        return CompiledComposite.apply(
            means2d, conics, opacities, colors, depths, half.detach(), cam, num_cameras, width, height
        )


def _numba_unavailable() -> str | None:
    import importlib.util

    if importlib.util.find_spec("numba") is None:
        return "numba: not installed (pip install numba)"
    return None


@register("rasterizer", "numba", requires=_numba_unavailable)
class NumbaRasterizer(Rasterizer):
    """torch_ref's contract; forward-only renders compiled whole, gradient renders with compiled projection and
    compositing (their backward passes compiled too)."""

    def __init__(self) -> None:
        self._reference = _CompiledTraining()

    def set_execution(self, execution: Execution) -> None:
        super().set_execution(execution)
        self._reference.set_execution(execution)

    def _renders_compiled(self, tensors: tuple[Tensor, ...]) -> bool:
        """Whether a render of these tensors runs the compiled loops whole: the execution compiles the first (CPU,
        float32 or float64), no gradient asked."""
        if not self.execution.compiled(tensors[0]):
            return False
        return not (torch.is_grad_enabled() and any(t.requires_grad for t in tensors))

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
        if not self._renders_compiled((means, quats, scales, opacities, sh)) or cameras.device.type != "cpu":
            return self._reference.render(
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
        # here, not at module level: plugin discovery imports every backend, and numba's import costs about 0.5 s
        from framework.kernels import rasterize
        from framework.kernels.rasterize import float64_array as _np64
        from framework.kernels.sh_colours import sh_colours_compiled

        C, N, H, W = cameras.num, means.shape[0], cameras.height, cameras.width
        dtype = means.dtype
        means2d = np.empty((C, N, 2))  # [C, N, 2] (float64 throughout; cast back at the end)
        conics = np.empty((C, N, 3))  # [C, N, 3]
        depths = np.empty((C, N))  # [C, N]
        half = np.empty((C, N, 2))  # [C, N, 2] screen-box half extents, 0 where culled
        radii = np.empty((C, N), dtype=np.int32)  # [C, N]
        valid = np.empty((C, N), dtype=np.bool_)  # [C, N]
        opacity = _np64(opacities)  # [N]
        rasterize.project(
            _np64(means),
            _np64(quats),
            _np64(scales),
            opacity,
            _np64(cameras.K),
            _np64(cameras.world_to_cam),
            W,
            H,
            float(near),
            float(far),
            EPS2D,
            means2d,
            conics,
            depths,
            half,
            radii,
            valid,
            np.empty((C, N, 3)),
        )
        centers = cameras.centers().to(dtype)  # [C, 3]
        colors = sh_colours_compiled(sh_degree, sh, means, centers)  # [C, N, 3] float64
        bg = np.zeros(3) if background is None else _np64(background.reshape(3))  # [3]
        image_dtype = np.float32 if dtype == torch.float32 else np.float64  # sums in float64, stored as the caller's
        rgb = np.empty((C, H, W, 3), dtype=image_dtype)  # [C, H, W, 3]
        alpha = np.empty((C, H, W), dtype=image_dtype)  # [C, H, W]
        depth = np.empty((C, H, W), dtype=image_dtype)  # [C, H, W]
        for c in range(C):
            visible = np.flatnonzero(valid[c])
            order = visible[np.argsort(depths[c, visible], kind="stable")]  # nearest first, ties in Gaussian order
            rasterize.composite(
                order,
                means2d[c],
                conics[c],
                opacity,
                colors[c],
                depths[c],
                half[c],
                W,
                H,
                bg,
                rgb[c],
                alpha[c],
                depth[c],
            )
        out = (torch.from_numpy(a).to(dtype) for a in (rgb, alpha[..., None], depth[..., None], means2d))
        rgb_t, alpha_t, depth_t, means2d_t = out
        return RenderOutput(rgb=rgb_t, alpha=alpha_t, depth=depth_t, means2d=means2d_t, radii=torch.from_numpy(radii))

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
        """torch_ref's (pruning's pass over the training views; not a real-time path)."""
        return self._reference.blend_weights(means, quats, scales, opacities, cameras, near=near, far=far)

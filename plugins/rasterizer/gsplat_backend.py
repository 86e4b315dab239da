"""`gsplat`: the CUDA kernels of gsplat 1.5.3 (`gsplat.rasterization`) behind our `Rasterizer` interface.

Available only when `torch.cuda.is_available()` and gsplat imports. gsplat is never imported at module import time:
on a machine with an `nvcc` stub but no CUDA device its first use tries a JIT build and fails with an ImportError
about a missing `.so` that says nothing about the real cause (see DESIGN.md), so the availability check looks at
CUDA first and only then imports the package.

Mapping of gsplat's outputs (rendering.py, 1.5.3, `packed=False`):
- colours: `render_mode="RGB+D"` gives [C, H, W, 4]; the last channel is the accumulated z, sum_i T_i alpha_i z_i,
  which is our non-normalised `depth`; the background gets a 0 depth channel inside gsplat.
- alphas [C, H, W, 1] -> `alpha`.
- `info["means2d"]` [C, N, 2] -> `means2d` with `retain_grad()` (gsplat's own strategies read the same tensor).
- `info["radii"]` is [C, N, 2] (per axis) in 1.5.3 and [C, N] in older releases -> max over the last axis.
- SH: `colors=sh [N, K, 3]` with `sh_degree`; gsplat evaluates at mean - camera centre, adds 0.5 and clamps at 0,
  as our spec does.

Intrinsic differences from `torch_ref` (the conformance suite tolerates none of them on its scenes):
- Per-pixel set: gsplat tests every pixel of every 16x16 tile touched by a Gaussian's opacity-aware box
  (extend = min(3.33, sqrt(2 ln(255 opacity))), the same box as ours) with the same alpha >= 1/255 and sigma >= 0
  tests, so the pairs that contribute are the same set (the box holds every pixel that can pass the test).
- Near/far culling: gsplat culls z < near or z > far; we cull z <= near or z >= far (differs only at equality).
- `means2d` of culled Gaussians is whatever gsplat leaves there (not the projected centre); compare where radii > 0.
- float32 only, with CUDA fast-math exp/log: float64 inputs are computed in float32 and cast back.
- Intrinsics get no gradient (gsplat does not differentiate w.r.t. Ks); neither does the background here.
"""

from __future__ import annotations

import importlib.util
import logging
import warnings

import torch
from torch import Tensor

from framework.interfaces.rasterizer import EPS2D, FAR_PLANE, NEAR_PLANE, Rasterizer
from framework.registry import register
from framework.types import Cameras, RenderOutput

log = logging.getLogger(__name__)

REASON_NO_CUDA = "gsplat: no CUDA device (torch.cuda.is_available() is False)"
REASON_NOT_INSTALLED = "gsplat: not installed (pip install 'splatrig[cuda]')"
COMPILE_WARNING = (
    "gsplat: the first rasterization compiles gsplat's CUDA kernels (several minutes, once per machine; cached "
    "under ~/.cache/torch_extensions)."
)

_warned_compile = False


def gsplat_unavailable() -> str | None:
    """None when gsplat can run here, else why not (CUDA is checked first: see the module docstring)."""
    if not torch.cuda.is_available():
        return REASON_NO_CUDA
    if importlib.util.find_spec("gsplat") is None:
        return REASON_NOT_INSTALLED
    try:  # safe now that a CUDA device exists; catches e.g. gsplat 1.5.3's undeclared `packaging` dependency
        import gsplat  # noqa: F401
    except ImportError as exc:
        return f"{REASON_NOT_INSTALLED}; importing it failed: {exc}"
    return None


def _warn_compile_once() -> None:
    global _warned_compile
    if not _warned_compile:
        _warned_compile = True
        warnings.warn(COMPILE_WARNING, RuntimeWarning, stacklevel=3)
        log.warning(COMPILE_WARNING)


def _rasterization():
    """`gsplat.rasterization`, imported on first use (a function so tests can substitute it)."""
    from gsplat import rasterization

    return rasterization


def max_radius(radii: Tensor) -> Tensor:
    """gsplat radii [C, N, 2] (1.5.x) or [C, N] (older) -> [C, N] int32."""
    if radii.dim() == 3:
        radii = radii.amax(dim=-1)
    return radii.to(torch.int32)


@register("rasterizer", "gsplat", requires=gsplat_unavailable)
class GsplatRasterizer(Rasterizer):
    """gsplat's tiled CUDA rasterizer. `absgrad=True` also fills `means2d.absgrad` (AbsGS densification)."""

    def __init__(self, packed: bool = False, absgrad: bool = False, tile_size: int = 16) -> None:
        self.packed = packed
        self.absgrad = absgrad
        self.tile_size = tile_size

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
        _warn_compile_once()
        rasterization = _rasterization()
        out_dtype = means.dtype
        dev = means.device
        C, N, H, W = cameras.num, means.shape[0], cameras.height, cameras.width
        f32 = [x.float() for x in (means, quats, scales, opacities, sh)]
        viewmats = cameras.world_to_cam.to(dev, torch.float32)  # [C, 4, 4]
        Ks = cameras.K.to(dev, torch.float32)  # [C, 3, 3]
        bg = None
        if background is not None:
            bg = background.to(dev, torch.float32).reshape(1, 3).expand(C, 3).contiguous()  # [C, 3]
        colors, alphas, info = rasterization(
            f32[0],
            f32[1],
            f32[2],
            f32[3],
            f32[4],
            viewmats,
            Ks,
            W,
            H,
            near_plane=near,
            far_plane=far,
            eps2d=EPS2D,
            sh_degree=sh_degree,
            packed=self.packed,
            tile_size=self.tile_size,
            backgrounds=bg,
            render_mode="RGB+D",
            absgrad=self.absgrad,
            rasterize_mode="classic",
        )
        means2d = info["means2d"]  # [C, N, 2] (unpacked) or [nnz, 2] (packed)
        radii = info["radii"]
        if self.packed:
            means2d, radii = self._unpack(info, C, N)
        elif means2d.requires_grad:
            means2d.retain_grad()
        return RenderOutput(
            rgb=colors[..., :3].to(out_dtype),  # [C, H, W, 3]
            alpha=alphas.to(out_dtype),  # [C, H, W, 1]
            depth=colors[..., 3:4].to(out_dtype),  # [C, H, W, 1] accumulated z
            means2d=means2d,
            radii=max_radius(radii),
        )

    @staticmethod
    def _unpack(info: dict, C: int, N: int) -> tuple[Tensor, Tensor]:
        """Packed mode returns [nnz, ...] rows for (camera_ids, gaussian_ids); scatter them into [C, N, ...].

        The image depends on the packed means2d, not on a scattered copy, so the copy is a leaf whose `.grad` a hook
        on the packed tensor fills with the scattered dL/d(means2d) during backward (zeros where not visible)."""
        cam, gid = info["camera_ids"], info["gaussian_ids"]
        packed = info["means2d"]  # [nnz, 2]
        dense = packed.detach().new_zeros(C, N, 2).index_put((cam, gid), packed.detach())
        if packed.requires_grad:
            dense.requires_grad_(True)

            def scatter_grad(g: Tensor) -> None:
                gd = g.new_zeros(C, N, 2).index_put((cam, gid), g, accumulate=True)
                dense.grad = gd if dense.grad is None else dense.grad + gd

            packed.register_hook(scatter_grad)
        r = info["radii"]
        r = r.amax(-1) if r.dim() == 2 else r
        radii = torch.zeros(C, N, dtype=torch.int32, device=r.device).index_put((cam, gid), r.to(torch.int32))
        return dense, radii

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
- `info["radii"]` is [C, N, 2] (per axis) in 1.5.3 and [C, N] in older releases -> the larger of the two, 0 where
  either is 0.
- SH: `colors=sh [N, K, 3]` with `sh_degree`; gsplat evaluates at mean - camera centre, adds 0.5 and clamps at 0,
  as our spec does.

What gsplat does differently, and what this wrapper does about it (read from gsplat 1.5.3's source):
- Inputs: gsplat's own checks are bare `assert`s; `check_render_inputs` runs first, as in `torch_ref`, and inputs are
  handed over contiguous (the CUDA entry points reject strided tensors; 1.5.3's Python wrappers also copy them).
- Quaternions: gsplat normalises with rsqrt(|q|^2) in float32, so a zero quaternion, or one whose |q|^2 underflows,
  gives a NaN covariance. Every culling test is False for NaN, so the Gaussian is kept with radius (int)NaN (0 on
  the GPU as we read it, hence dropped; docs/results/gpu.md), where the contract draws it with the identity
  rotation. Quaternions are normalised here first, with the same `quat_normalize` as `torch_ref`.
- Near/far: gsplat culls z < near or z > far (float32); the contract culls z <= near or z >= far. The planes are
  passed as the next float32 inward, which makes the two rules agree for every float32 depth.
- `means2d` rows of culled Gaussians are never written (the tensor comes from `at::empty`): they are zeroed here,
  through `.data` so autograd's version counters are left alone. gsplat's rasterizer saved the same tensor for its
  backward, but it only reads the rows of Gaussians with radii > 0, which are untouched.
- Packed mode returns [nnz, ...] rows; they are scattered into [C, N, ...]. The dense `means2d` is a detached leaf
  (the image depends on the packed rows, not on it): its `.grad`, and `.absgrad` with `absgrad=True`, are filled
  by a hook on the packed tensor during backward. A loss on it does not reach the Gaussians; use `packed=False`
  for that.
- Per-pixel set: gsplat tests every pixel of every 16x16 tile touched by a Gaussian's opacity-aware box
  (extend = min(3.33, sqrt(2 ln(255 opacity))), the same box as ours) with the same alpha >= 1/255 and sigma >= 0
  tests, so the pairs that contribute are the same set (the box holds every pixel that can pass the test).
- A Gaussian is drawn only if both per-axis radii are > 0 (`isect_tiles`); the returned radius is 0 otherwise.
- float32 only, with CUDA fast-math exp/log: float64 inputs are computed in float32 and cast back
  (`supports_float64 = False`, so the conformance suite checks gradients with float32 steps and tolerances).
- The conic is 1 / (a c - b^2) of the float32 screen covariance: about kappa * eps32 relative error for a covariance
  of condition number kappa (a needle-thin Gaussian; measured on an H200: alpha off by 3.9e-4 at kappa 2e4, where
  torch_ref, which forms the determinant without the cancellation, is within 7e-8). `conic_from_float32_covariance`
  tells the conformance suite so.
- Intrinsics get no gradient (gsplat does not differentiate w.r.t. Ks); neither does the background here.
"""

from __future__ import annotations

import importlib.util
import logging
import math
import warnings

import torch
from torch import Tensor

from framework.geometry import quat_normalize
from framework.interfaces.rasterizer import EPS2D, FAR_PLANE, NEAR_PLANE, Rasterizer, check_render_inputs
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


def max_radius(radii: Tensor, per_axis: bool) -> Tensor:
    """gsplat radii [..., 2] (1.5.x, per axis) or [...] (older releases) -> [...] int32. 0 unless gsplat draws the
    Gaussian: its `isect_tiles` skips one whose radius along either axis is 0."""
    if per_axis:
        radii = torch.where((radii > 0).all(dim=-1), radii.amax(dim=-1), torch.zeros_like(radii[..., 0]))
    return radii.to(torch.int32)


def inward_planes(near: float, far: float) -> tuple[float, float]:
    """The planes to hand gsplat so that its rule (cull z < near or z > far, in float32) culls what ours does
    (z <= near or z >= far): the next float32 above `near` and below `far`."""
    n32 = torch.tensor(near, dtype=torch.float32)
    f32 = torch.tensor(far, dtype=torch.float32)
    near_in = torch.nextafter(n32, torch.tensor(math.inf, dtype=torch.float32))
    far_in = torch.nextafter(f32, torch.tensor(-math.inf, dtype=torch.float32))
    return float(near_in), float(far_in)


def _empty_render(
    inputs: list[Tensor], C: int, H: int, W: int, bg: Tensor | None, out_dtype: torch.dtype
) -> RenderOutput:
    """What a scene with no Gaussians renders to: the background, zero alpha and depth, no screen rows.

    gsplat 1.5.3 is never called with N = 0: its projection divides by N on the host (`means.numel() / (N * 3)` in
    `fully_fused_projection`), which killed the process with SIGFPE on an H200. The outputs hang on the inputs
    through a zero sum, so a loss over them back-propagates (zero, empty gradients) as with any other scene."""
    zero = sum(x.sum() for x in inputs) * 0.0  # [] 0, in the inputs' graph
    dev = inputs[0].device
    rgb = torch.zeros(C, H, W, 3, device=dev) if bg is None else bg[:, None, None, :].expand(C, H, W, 3)
    flat = torch.zeros(C, H, W, 1, device=dev)
    return RenderOutput(
        rgb=(rgb + zero).to(out_dtype),  # [C, H, W, 3]
        alpha=(flat + zero).to(out_dtype),  # [C, H, W, 1]
        depth=(flat + zero).to(out_dtype),  # [C, H, W, 1]
        means2d=torch.zeros(C, 0, 2, device=dev),  # [C, 0, 2]
        radii=torch.zeros(C, 0, dtype=torch.int32, device=dev),  # [C, 0]
    )


@register("rasterizer", "gsplat", requires=gsplat_unavailable)
class GsplatRasterizer(Rasterizer):
    """gsplat's tiled CUDA rasterizer. `absgrad=True` also fills `means2d.absgrad` (AbsGS densification)."""

    #: gsplat's kernels compute in float32 (see the module docstring).
    supports_float64 = False
    conic_from_float32_covariance = True  # ProjectionEWA3DGSFused.cu: det = a c - b^2, float32

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
        check_render_inputs(means, quats, scales, opacities, sh, sh_degree)
        _warn_compile_once()
        rasterization = _rasterization()
        out_dtype = means.dtype
        dev = means.device
        C, N, H, W = cameras.num, means.shape[0], cameras.height, cameras.width
        unit_quats = quat_normalize(quats.float())  # [N, 4]; zero -> identity, as torch_ref (not NaN, as gsplat)
        f32 = [x.float().contiguous() for x in (means, unit_quats, scales, opacities, sh)]
        viewmats = cameras.world_to_cam.to(dev, torch.float32).contiguous()  # [C, 4, 4]
        Ks = cameras.K.to(dev, torch.float32).contiguous()  # [C, 3, 3]
        bg = None
        if background is not None:
            bg = background.to(dev, torch.float32).reshape(1, 3).expand(C, 3).contiguous()  # [C, 3]
        if N == 0:
            return _empty_render(f32, C, H, W, bg, out_dtype)
        near_in, far_in = inward_planes(near, far)
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
            near_plane=near_in,
            far_plane=far_in,
            eps2d=EPS2D,
            sh_degree=sh_degree,
            packed=self.packed,
            tile_size=self.tile_size,
            backgrounds=bg,
            render_mode="RGB+D",
            absgrad=self.absgrad,
            rasterize_mode="classic",
        )
        if self.packed:
            means2d, radii = self._unpack(info, C, N)
        else:
            means2d = info["means2d"]  # [C, N, 2]
            radii = max_radius(info["radii"], per_axis=info["radii"].dim() == 3)  # [C, N]
            # Culled rows were never written: zero them in place through .data (no version bump), leaving the
            # rows gsplat's backward reads (radii > 0) as they are.
            means2d.data.masked_fill_((radii == 0).unsqueeze(-1), 0.0)
            if means2d.requires_grad:
                means2d.retain_grad()
        return RenderOutput(
            rgb=colors[..., :3].to(out_dtype),  # [C, H, W, 3]
            alpha=alphas.to(out_dtype),  # [C, H, W, 1]
            depth=colors[..., 3:4].to(out_dtype),  # [C, H, W, 1] accumulated z
            means2d=means2d,
            radii=radii,
        )

    @staticmethod
    def _unpack(info: dict, C: int, N: int) -> tuple[Tensor, Tensor]:
        """Packed mode returns [nnz, ...] rows for (camera_ids, gaussian_ids); scatter them into [C, N, ...].

        The image depends on the packed means2d, not on a scattered copy, so the copy is a detached leaf whose
        `.grad` (and `.absgrad`, which gsplat's backward sets on the packed tensor) a hook on the packed tensor
        fills with the scattered values during backward (zeros where not visible)."""
        cam, gid = info["camera_ids"], info["gaussian_ids"]
        packed = info["means2d"]  # [nnz, 2]
        dense = packed.detach().new_zeros(C, N, 2).index_put((cam, gid), packed.detach())  # [C, N, 2]
        if packed.requires_grad:
            dense.requires_grad_(True)

            def scatter(rows: Tensor) -> Tensor:
                return rows.new_zeros(C, N, 2).index_put((cam, gid), rows, accumulate=True)

            def scatter_grad(g: Tensor) -> None:
                gd = scatter(g)
                dense.grad = gd if dense.grad is None else dense.grad + gd
                absgrad = getattr(packed, "absgrad", None)  # set by gsplat's rasterizer backward, which ran first
                if absgrad is not None:
                    dense.absgrad = scatter(absgrad)

            packed.register_hook(scatter_grad)
        r = info["radii"]
        radii = torch.zeros(C, N, dtype=torch.int32, device=r.device)
        radii = radii.index_put((cam, gid), max_radius(r, per_axis=r.dim() == 2))
        return dense, radii

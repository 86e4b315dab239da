"""`jax`: the rasterizer written in JAX (`jax.jit`, gradients by `jax.vjp`), bridged to torch autograd.

One render is three steps, two of them jitted JAX programs with static shapes:
1. `framework.splat.jax_raster.project` (JAX): EWA projection, SH colour and the screen box for C cameras x N Gaussians.
   N is padded to a bucket (4 per octave) so densification recompiles only a handful of times.
2. Pair list (torch, no gradient): every (Gaussian, pixel) pair in the boxes with alpha >= 1/255, sorted by
   (camera, pixel, depth) with one integer sort. This is a discrete function with no gradient, and torch's CPU
   sort is about 10x faster than JAX's, so it stays in torch. The list is padded to a bucket (4 per octave).
3. `framework.splat.jax_raster.composite` (JAX): front-to-back compositing over the sorted pairs.

Each JAX step is one `torch.autograd.Function` whose forward runs `jax.vjp` and whose backward calls the saved VJP
function. The projected centres `means2d` are a real tensor between the two Functions, so `RenderOutput.means2d.grad`
is exactly dL/d(means2d), as densification needs. Tensors cross by DLPack (zero-copy where both sides share the
device); float64 inputs run under `jax.enable_x64(True)` so gradient checks are possible; float16/bfloat16 inputs
are computed in float32 and the outputs cast back. Cameras get no gradient (unlike `torch_ref`).

Where the time goes, in order: compositing forward and backward (gathers, one segmented scan, three segment sums),
the pair list (enumerating box pixels and the alpha prefilter, then an int32 stable sort), projection + SH; DLPack
transfers are zero-copy both ways on a CPU. Compiles take seconds per new shape bucket and are cached on disk
(`compilation_cache`). `tools/bench_rasterizers.py` times it beside the other backends.

On a machine with more busy threads than cores, start Python with `OMP_WAIT_POLICY=PASSIVE`: torch's OpenMP
workers otherwise spin between ops and starve JAX's threads (and each other); we measured 3-10x slower steps for
both this backend and `torch_ref` without it.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterator
from typing import Any

import torch
from torch import Tensor

from framework.interfaces.rasterizer import FAR_PLANE, NEAR_PLANE, Rasterizer
from framework.registry import register
from framework.splat.bands import row_bands
from framework.splat.pairs import depth_ordered_entries, enumerate_pairs, sort_pairs_by_pixel
from framework.types import Cameras, RenderOutput

log = logging.getLogger(__name__)

MIN_PAIR_BUCKET = 4096  # small scenes (tests, previews) share one compiled shape
MIN_GAUSSIAN_BUCKET = 256


def _jax_unavailable() -> str | None:
    """Looks for jax and jaxlib without importing them: importing jax costs ~2 s, paid only when jax renders."""
    import importlib.util

    if importlib.util.find_spec("jax") is None or importlib.util.find_spec("jaxlib") is None:
        return "jax: not installed (pip install 'splatrig[jax]')"
    return None


def bucket(n: int, minimum: int) -> int:
    """Smallest size >= n of the form 2^k * {1, 1.25, 1.5, 1.75} (and >= minimum): at most 25% padding and four
    compiled shapes per doubling of n."""
    n = max(int(n), minimum)
    base = 1 << (n.bit_length() - 1)  # largest power of two <= n
    step = max(base // 4, 1)
    return -(-n // step) * step


def enable_compilation_cache() -> None:
    """Keep compiled XLA programs on disk (`<cache_dir>/jax`) so a new process skips the seconds-long compiles.

    Respects a cache directory the user already configured."""
    import jax

    from framework.paths import cache_dir

    if jax.config.jax_compilation_cache_dir is None:
        path = cache_dir() / "jax"
        path.mkdir(parents=True, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", str(path))


# ----------------------------------------------------------------------------------------------------------------
# torch <-> JAX bridge
# ----------------------------------------------------------------------------------------------------------------


def _jax_device_for(device: torch.device):
    """The JAX device holding arrays for a torch device: the same GPU where jaxlib has CUDA, else the CPU."""
    import jax

    if device.type == "cuda":
        try:
            gpus = jax.devices("gpu")
        except RuntimeError:
            gpus = []
        if gpus:
            return gpus[device.index or 0]
    return jax.devices("cpu")[0]


def to_jax(t: Tensor, jdev) -> Any:
    """torch -> JAX without a copy where DLPack allows it (same device, supported dtype), else through numpy."""
    import jax

    t = t.detach()
    if t.dtype == torch.bool:
        t = t.to(torch.uint8)
    on_gpu = jdev.platform == "gpu"
    if t.device.type == "cuda" and not on_gpu:
        t = t.cpu()
    t = t.contiguous()
    try:
        return jax.dlpack.from_dlpack(t)
    except Exception:  # unsupported stride/alignment/dtype: copy through host memory
        return jax.device_put(t.cpu().numpy(), jdev)


def to_torch(a: Any, device: torch.device) -> Tensor:
    """JAX -> torch (zero-copy by DLPack where possible), moved to `device`."""
    try:
        t = torch.from_dlpack(a)
    except Exception:
        import numpy as np

        t = torch.from_numpy(np.asarray(a).copy())
    return t.to(device)


@contextlib.contextmanager
def _precision(dtype: torch.dtype) -> Iterator[None]:
    """float64 tensors need JAX's x64 mode (scoped, so other JAX users keep their default)."""
    import jax

    if dtype == torch.float64:
        with jax.enable_x64(True):
            yield
    else:
        yield


# ----------------------------------------------------------------------------------------------------------------
# autograd Functions wrapping the two JAX programs
# ----------------------------------------------------------------------------------------------------------------


def _cotangent(g: Tensor | None, like: Any, jdev) -> Any:
    import jax.numpy as jnp

    if g is None:
        return jnp.zeros(like.shape, like.dtype)
    return to_jax(g, jdev)


class _Project(torch.autograd.Function):
    """(means, quats, scales, sh) -> (means2d, conics, depths, colors) + non-differentiable (half, radii)."""

    @staticmethod
    def forward(ctx: Any, means, quats, scales, sh, opacities, viewmats, Ks, cfg: dict):  # type: ignore[override]
        import jax

        from framework.splat.jax_raster import project

        jdev = cfg["jdev"]
        dev = means.device
        with _precision(means.dtype):
            args = [to_jax(x, jdev) for x in (means, quats, scales, sh)]
            const = [to_jax(x, jdev) for x in (opacities, viewmats, Ks)]
            near = jax.numpy.asarray(cfg["near"], dtype=args[0].dtype)
            far = jax.numpy.asarray(min(cfg["far"], 3e38), dtype=args[0].dtype)

            def f(m, q, s, c):
                return project(m, q, s, c, *const, near, far, **cfg["static"])

            if cfg["needs_grad"]:
                outs, vjp_fn, aux = jax.vjp(f, *args, has_aux=True)
                ctx.vjp_fn = vjp_fn
                ctx.primal_outs = outs
            else:
                outs, aux = f(*args)
            ctx.jdev = jdev
            ctx.dtype = means.dtype
            # outputs are cloned (small: [C, N, ...]) so an in-place edit in torch can never reach JAX's residuals
            res = tuple(to_torch(o, dev).clone() for o in outs) + tuple(to_torch(a, dev) for a in aux)
        ctx.mark_non_differentiable(res[4], res[5])
        return res

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, g_m2d, g_conic, g_depth, g_color, _g_half, _g_radii):  # type: ignore[override]
        dev = g_m2d.device if g_m2d is not None else None
        with _precision(ctx.dtype):
            gs = (g_m2d, g_conic, g_depth, g_color)
            cts = tuple(_cotangent(g, o, ctx.jdev) for g, o in zip(gs, ctx.primal_outs, strict=True))
            grads = ctx.vjp_fn(cts)
            out = tuple(to_torch(g, dev or torch.device("cpu")) for g in grads)
        return (*out, None, None, None, None)


class _Composite(torch.autograd.Function):
    """Per-(camera, Gaussian) screen quantities + sorted pairs -> per-pixel (rgb, alpha, depth)."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, means2d, conics, depths, colors, opacities, background, gauss_idx, pixel_idx, starts, cfg: dict
    ):
        import jax

        from framework.splat.jax_raster import composite

        jdev = cfg["jdev"]
        dev = means2d.device
        with _precision(means2d.dtype):
            args = [to_jax(x, jdev) for x in (means2d, conics, depths, colors, opacities, background)]
            idx = [to_jax(x, jdev) for x in (gauss_idx, pixel_idx)] + [to_jax(starts, jdev).astype(bool)]

            def f(*a):
                return composite(*a, *idx, **cfg["static"])

            if cfg["needs_grad"]:
                outs, vjp_fn = jax.vjp(f, *args)
                ctx.vjp_fn = vjp_fn
                ctx.primal_outs = outs
            else:
                outs = f(*args)
            ctx.jdev = jdev
            ctx.dtype = means2d.dtype
            return tuple(to_torch(o, dev).clone() for o in outs)  # small images; see _Project

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, g_rgb, g_alpha, g_depth):  # type: ignore[override]
        dev = next(g.device for g in (g_rgb, g_alpha, g_depth) if g is not None)
        with _precision(ctx.dtype):
            gs = (g_rgb, g_alpha, g_depth)
            cts = tuple(_cotangent(g, o, ctx.jdev) for g, o in zip(gs, ctx.primal_outs, strict=True))
            grads = ctx.vjp_fn(cts)
            out = tuple(to_torch(g, dev) for g in grads)
        return (*out, None, None, None, None)


# ----------------------------------------------------------------------------------------------------------------
# the pair list (torch, no gradient)
# ----------------------------------------------------------------------------------------------------------------


def build_pairs(
    means2d: Tensor,  # [C, Np, 2] detached
    conics: Tensor,  # [C, Np, 3]
    depths: Tensor,  # [C, Np]
    half: Tensor,  # [C, Np, 2] box half extents, 0 where culled
    radii: Tensor,  # [C, Np]
    opacities: Tensor,  # [Np]
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """(gauss_idx [P] into C*Np, pixel_idx [P] into C*H*W) of the pairs that can reach alpha >= 1/255, sorted by
    (camera, pixel, depth): the same pairs as torch_ref (framework.splat.pairs); the JAX compositor applies the exact
    alpha test, so the enumeration's conservative margin only costs a few extra pairs."""
    C, Np = depths.shape
    flat, cam, gid = depth_ordered_entries(radii > 0, depths)  # [M] visible entries in depth order
    ent, pix = enumerate_pairs(
        means2d.reshape(-1, 2)[flat],
        conics.reshape(-1, 3)[flat],
        opacities[gid],
        half.reshape(-1, 2)[flat],
        cam,
        width,
        height,
    )
    if pix.shape[0] >= 2**31 or C * height * width >= 2**31:
        raise ValueError(
            f"jax rasterizer: {pix.shape[0]} (Gaussian, pixel) pairs for {C} cameras of {width}x{height} exceed the "
            "int32 indices of the compositor; render fewer cameras per call or a smaller image."
        )
    ent, pix = sort_pairs_by_pixel(ent, pix, C * height * width)
    return flat[ent], pix


def pad_pairs(gauss_idx: Tensor, pixel_idx: Tensor, num_pixels: int) -> tuple[Tensor, Tensor, Tensor]:
    """Pad to a bucket with pairs in the dummy pixel `num_pixels`; int32 ids and the segment-start flags."""
    P = gauss_idx.shape[0]
    Pp = bucket(P, MIN_PAIR_BUCKET)
    dev = gauss_idx.device
    g = torch.zeros(Pp, dtype=torch.int32, device=dev)
    p = torch.full((Pp,), num_pixels, dtype=torch.int32, device=dev)
    g[:P] = gauss_idx
    p[:P] = pixel_idx
    starts = torch.ones(Pp, dtype=torch.bool, device=dev)
    starts[1:] = p[1:] != p[:-1]
    return g, p, starts


def _pad_rows(x: Tensor, n: int, fill: float = 0.0) -> Tensor:
    """Pad dim 0 (or dim 1 for [C, N, ...]) to n rows."""
    if x.shape[0] == n:
        return x
    pad = x.new_full((n - x.shape[0], *x.shape[1:]), fill)
    return torch.cat([x, pad], dim=0)


# ----------------------------------------------------------------------------------------------------------------
# the component
# ----------------------------------------------------------------------------------------------------------------


@register("rasterizer", "jax", requires=_jax_unavailable)
class JaxRasterizer(Rasterizer):
    """Rasterizer in JAX (CPU here; GPU where jaxlib has CUDA), same results as `torch_ref`.

    `profile=True` records wall times of the forward stages of the last call in `self.last_profile` (ms), with
    synchronisation between stages (slower; for measurements only).
    """

    def __init__(self, compilation_cache: bool = True, profile: bool = False) -> None:
        if compilation_cache:
            enable_compilation_cache()
        self.profile = profile
        self.last_profile: dict[str, float] = {}
        self._shapes_seen: set[tuple] = set()

    def _tick(self, name: str, t0: float) -> float:
        t = time.perf_counter()
        if self.profile:
            self.last_profile[name] = self.last_profile.get(name, 0.0) + 1e3 * (t - t0)
        return t

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
        k = (sh_degree + 1) ** 2
        if not 0 <= sh_degree <= 3 or sh.shape[-2] < k:
            raise ValueError(
                f"jax rasterizer: sh_degree must be in 0..3 with sh [N, >= (sh_degree+1)^2, 3]; got sh_degree="
                f"{sh_degree} and sh of shape {tuple(sh.shape)}. Lower sh_degree or allocate more coefficients."
            )
        out_dtype = means.dtype
        dtype = torch.float64 if out_dtype == torch.float64 else torch.float32
        dev = means.device
        C, N, H, W = cameras.num, means.shape[0], cameras.height, cameras.width
        means, quats, scales, opacities = (x.to(dtype) for x in (means, quats, scales, opacities))
        sh = sh[:, :k].to(dtype)  # only the active bands: fewer compiled shapes and less to move
        K = cameras.K.to(dev, dtype)
        w2c = cameras.world_to_cam.to(dev, dtype)
        bg = torch.zeros(3, dtype=dtype, device=dev) if background is None else background.to(dev, dtype)
        jdev = _jax_device_for(dev)
        needs_grad = torch.is_grad_enabled() and any(x.requires_grad for x in (means, quats, scales, opacities, sh, bg))
        self.last_profile = {}
        t0 = time.perf_counter()

        # 1. projection on N padded to a bucket (padding: unit Gaussians with zero opacity, culled by the box rule)
        Np = bucket(N, MIN_GAUSSIAN_BUCKET)
        ident = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype, device=dev)
        pm = _pad_rows(means, Np)
        pq = torch.cat([quats, ident.expand(Np - N, 4)]) if Np > N else quats
        ps = _pad_rows(scales, Np, 1.0)
        po = _pad_rows(opacities, Np)
        psh = _pad_rows(sh, Np)
        static = {"width": W, "height": H, "sh_degree": sh_degree}
        self._note_shape(("project", dtype, C, Np, k, W, H, sh_degree))
        cfg = {"jdev": jdev, "near": near, "far": far, "static": static, "needs_grad": needs_grad}
        m2d_p, conics, depths, colors, half, radii_p = _Project.apply(pm, pq, ps, psh, po, w2c, K, cfg)
        means2d = m2d_p[:, :N]  # [C, N, 2]
        if means2d.requires_grad:
            means2d.retain_grad()
        t0 = self._tick("project_ms", t0)

        # 2. + 3. per row band (one band unless the image is huge; framework.splat.bands): sorted pair list in torch,
        # then compositing; means2d re-enters padded so the compiled shape depends on the bucket only
        m2d_in = torch.cat([means2d, m2d_p[:, N:].detach()], dim=1) if Np > N else means2d
        drawn = radii_p.reshape(-1) > 0
        bands = row_bands(m2d_p.detach().reshape(-1, 2)[drawn], half.reshape(-1, 2)[drawn], W, H)
        shift = m2d_in.new_tensor([0.0, 1.0])
        parts = []
        hb = bands[0][1] - bands[0][0]  # every band is drawn hb rows tall (one compiled shape); the last is cropped
        for r0, r1 in bands:
            with torch.no_grad():
                m2d_band = m2d_p.detach() - r0 * shift
                gidx, pix = build_pairs(m2d_band, conics.detach(), depths.detach(), half, radii_p, po, W, hb)
                num_pixels = C * hb * W
                gidx, pix, starts = pad_pairs(gidx, pix, num_pixels)
            t0 = self._tick("pairs_ms", t0)
            if self.profile:
                self.last_profile["pairs"] = self.last_profile.get("pairs", 0.0) + float((pix < num_pixels).sum())
                self.last_profile["pairs_padded"] = self.last_profile.get("pairs_padded", 0.0) + float(pix.shape[0])
            op_cn = po.expand(C, Np)
            static_c = {"num_pixels": num_pixels, "width": W, "height": hb}
            self._note_shape(("composite", dtype, C * Np, pix.shape[0], num_pixels, W, hb))
            cfg_c = {"jdev": jdev, "static": static_c, "needs_grad": needs_grad}
            parts.append(
                _Composite.apply(
                    (m2d_in - r0 * shift).reshape(-1, 2),
                    conics.reshape(-1, 3),
                    depths.reshape(-1),
                    colors.reshape(-1, 3),
                    op_cn.reshape(-1),
                    bg,
                    gidx,
                    pix,
                    starts,
                    cfg_c,
                )
            )
            parts[-1] = tuple(x.reshape(C, hb, W, -1)[:, : r1 - r0] for x in parts[-1])
            t0 = self._tick("composite_ms", t0)
        rgb, alpha, depth = (torch.cat([p[i] for p in parts], dim=1) for i in range(3))
        out = RenderOutput(
            rgb=rgb.reshape(C, H, W, 3).to(out_dtype),
            alpha=alpha.reshape(C, H, W, 1).to(out_dtype),
            depth=depth.reshape(C, H, W, 1).to(out_dtype),
            means2d=means2d,
            radii=radii_p[:, :N],
        )
        return out

    def _note_shape(self, key: tuple) -> None:
        """Log the first use of each compiled shape (a JAX compile takes a second or more on a CPU)."""
        if key not in self._shapes_seen:
            self._shapes_seen.add(key)
            log.debug("jax rasterizer: new compiled shape %s", key)

    @property
    def compiled_shapes(self) -> int:
        """How many distinct (program, shape) combinations this instance has asked JAX to compile."""
        return len(self._shapes_seen)

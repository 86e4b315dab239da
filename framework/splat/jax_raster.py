"""Pure-JAX math of the `jax` rasterizer: EWA projection + SH colour, and compositing over (Gaussian, pixel) pairs.

The rules are those of `framework.interfaces.rasterizer` and mirror `framework.splat.projection` /
`framework.splat.sh` line by line, so the two backends agree to float rounding. Everything here has static shapes,
which is what `jax.jit` needs:

- `project` works on a padded Gaussian count (the caller pads N to a bucket so densification does not recompile).
- `composite` works on a padded list of pairs sorted by (camera, pixel, depth); the list itself is built outside JAX
  (it is a discrete, non-differentiable function of the projection, and torch's CPU sort is ~10x faster than JAX's).
  Padding pairs carry the pixel id `num_pixels` (one extra dummy segment) and never contribute.

Compositing works in log-transmittance: a segmented inclusive scan of log(1 - alpha) over each pixel's run of pairs
(`jax.lax.associative_scan` with segment-start flags, so there is no global cumulative sum whose magnitude would
swamp float32), then segment sums per pixel. Early termination ("next_T <= 1e-4 ends the pixel and that pair is not
added") becomes a mask: T only decreases along a run, so every pair from the terminating one on has
log T_incl <= log(1e-4).

This module imports jax at import time; only import it where jax is known to be installed.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from framework.guards import NORM_EPS
from framework.splat.contract import ALPHA_MAX, ALPHA_MIN, EPS2D, LOG_T_MIN
from framework.splat.projection import EXTEND_MAX, FOV_MARGIN
from framework.splat.sh import SH_C0, SH_C1, SH_C2, SH_C3


def quat_to_rotmat(q: jax.Array) -> jax.Array:
    """[N, 4] wxyz (any norm; zero -> identity, as framework.geometry) -> [N, 3, 3]."""
    n2 = jnp.sum(q * q, axis=-1, keepdims=True)
    ok = n2 > NORM_EPS**2
    qn = jnp.where(ok, q / jnp.sqrt(jnp.where(ok, n2, 1.0)), jnp.array([1.0, 0.0, 0.0, 0.0], q.dtype))
    w, x, y, z = qn[..., 0], qn[..., 1], qn[..., 2], qn[..., 3]
    rows = [
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    ]
    return jnp.stack(rows, axis=-1).reshape(*q.shape[:-1], 3, 3)


def sh_colors(degree: int, coeffs: jax.Array, dirs: jax.Array) -> jax.Array:
    """clamp(SH(dirs) + 0.5, 0): coeffs [..., K, 3], dirs [..., 3] (unnormalised) -> [..., 3]."""
    n2 = jnp.sum(dirs * dirs, axis=-1, keepdims=True)
    d = dirs / jnp.sqrt(jnp.maximum(n2, NORM_EPS**2))  # as torch's norm().clamp_min(1e-12), with a finite gradient at 0
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    basis = [jnp.full_like(x, SH_C0)]
    if degree >= 1:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        basis += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
        if degree >= 3:
            basis += [
                SH_C3[0] * y * (3.0 * xx - yy),
                SH_C3[1] * xy * z,
                SH_C3[2] * y * (4.0 * zz - xx - yy),
                SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
                SH_C3[4] * x * (4.0 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy),
                SH_C3[6] * x * (xx - 3.0 * yy),
            ]
    val = _weighted_basis_sum(jnp.stack(basis, axis=-1), coeffs[..., : len(basis), :])
    return jnp.maximum(val + 0.5, 0.0)


@jax.custom_vjp
def _weighted_basis_sum(basis: jax.Array, coeffs: jax.Array) -> jax.Array:
    """sum_k basis[..., k] * coeffs[..., k, :] -> [..., 3].

    Written as an unrolled sum (XLA fuses it into one loop) with a hand-written VJP (one broadcast product for the
    coefficients, one for the basis): letting JAX transpose the unrolled sum emits one padded full-size array per
    coefficient, and the stacked-broadcast form is ~3x slower forward; this is ~3x faster than either on CPU."""
    val = basis[..., 0, None] * coeffs[..., 0, :]
    for i in range(1, basis.shape[-1]):
        val = val + basis[..., i, None] * coeffs[..., i, :]
    return val


def _wbs_fwd(basis: jax.Array, coeffs: jax.Array) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
    return _weighted_basis_sum(basis, coeffs), (basis, coeffs)


def _wbs_bwd(res: tuple[jax.Array, jax.Array], g: jax.Array) -> tuple[jax.Array, jax.Array]:
    basis, coeffs = res  # [..., k], [..., k, 3] (coeffs may be broadcast over leading camera axes)
    g_basis = jnp.sum(coeffs * g[..., None, :], axis=-1)  # [..., k]
    g_coeffs = basis[..., :, None] * g[..., None, :]  # [C, N, k, 3]
    extra = g_coeffs.ndim - coeffs.ndim
    g_coeffs = jnp.sum(g_coeffs, axis=tuple(range(extra))) if extra else g_coeffs
    axes = tuple(i for i, (a, b) in enumerate(zip(g_coeffs.shape, coeffs.shape, strict=True)) if b == 1 and a != 1)
    g_coeffs = jnp.sum(g_coeffs, axis=axes, keepdims=True) if axes else g_coeffs
    return g_basis, g_coeffs


_weighted_basis_sum.defvjp(_wbs_fwd, _wbs_bwd)


@jax.custom_jvp
def quotient(x: jax.Array, y: jax.Array) -> jax.Array:
    """x / y whose derivative never forms y^2: JAX's own rule, -x / y^2, overflows float32 once y > 1.8e19 (the
    determinant of a Gaussian a few 1e5 px wide) and silently drops that term of the gradient. As torch's rule:
    d(x / y) = dx / y - ((x / y) / y) dy."""
    return x / y


@quotient.defjvp
def _quotient_jvp(primals: tuple[jax.Array, jax.Array], tangents: tuple[jax.Array, jax.Array]):
    x, y = primals
    dx, dy = tangents
    q = x / y
    return q, dx / y - (q / y) * dy


@partial(jax.jit, static_argnames=("width", "height", "sh_degree"))
def project(
    means: jax.Array,  # [N, 3]
    quats: jax.Array,  # [N, 4]
    scales: jax.Array,  # [N, 3]
    sh: jax.Array,  # [N, K, 3]
    opacities: jax.Array,  # [N] (only for the screen box, not differentiated)
    viewmats: jax.Array,  # [C, 4, 4]
    Ks: jax.Array,  # [C, 3, 3]
    near: jax.Array,  # [] scalar
    far: jax.Array,  # [] scalar
    *,
    width: int,
    height: int,
    sh_degree: int,
) -> tuple[tuple[jax.Array, jax.Array, jax.Array, jax.Array], tuple[jax.Array, jax.Array]]:
    """((means2d [C,N,2], conics [C,N,3], depths [C,N], colors [C,N,3]), (half_extents [C,N,2], radii [C,N] int32)).

    The first tuple is differentiable; the second is the discrete screen box (zeros where culled), returned as aux.
    """
    R = viewmats[:, :3, :3]  # [C, 3, 3]
    t = viewmats[:, :3, 3]  # [C, 3]
    p = jnp.sum(R[:, None, :, :] * means[None, :, None, :], axis=-1) + t[:, None, :]  # [C, N, 3]
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    in_depth = (z > near) & (z < far)
    z_safe = jnp.where(in_depth, z, 1.0)

    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]  # [C, 1]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    u = x / z_safe
    v = y / z_safe
    means2d = jnp.stack([fx * u + cx, fy * v + cy], axis=-1)  # [C, N, 2]

    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    u_c = jnp.minimum(jnp.maximum(u, -(cx / fx + FOV_MARGIN * tan_fovx)), (width - cx) / fx + FOV_MARGIN * tan_fovx)
    v_c = jnp.minimum(jnp.maximum(v, -(cy / fy + FOV_MARGIN * tan_fovy)), (height - cy) / fy + FOV_MARGIN * tan_fovy)
    rz = 1.0 / z_safe
    zero = jnp.zeros_like(z)
    J = jnp.stack([fx * rz, zero, -fx * u_c * rz, zero, fy * rz, -fy * v_c * rz], axis=-1)
    J = J.reshape(*z.shape, 2, 3)  # [C, N, 2, 3]

    RS = quat_to_rotmat(quats) * scales[:, None, :]  # [N, 3, 3]
    T = J @ (R[:, None] @ RS[None])  # [C, N, 2, 3]
    cov = T @ jnp.swapaxes(T, -1, -2)  # [C, N, 2, 2]
    cxx = cov[..., 0, 0] + EPS2D
    cxy = cov[..., 0, 1]
    cyy = cov[..., 1, 1] + EPS2D
    # without the cancellation of cxx cyy - cxy^2 (Lagrange's identity, as framework.splat.projection)
    det = jnp.sum(jnp.square(jnp.cross(T[..., 0, :], T[..., 1, :])), axis=-1) + EPS2D * (cxx + cyy - EPS2D)
    ok_det = det > 0
    det_safe = jnp.where(ok_det, det, 1.0)
    conics = quotient(jnp.stack([cyy, -cxy, cxx], axis=-1), det_safe[..., None])  # [C, N, 3]

    cam_pos = -jnp.sum(R * t[:, :, None], axis=1)  # [C, 3] camera centres in world space, -R^T t
    dirs = means[None, :, :] - cam_pos[:, None, :]  # [C, N, 3]
    colors = sh_colors(sh_degree, sh[None], dirs)  # [C, N, 3] (coefficients broadcast over cameras)

    # Discrete screen box (no gradient), exactly as framework.splat.projection computes it.
    op = jax.lax.stop_gradient(jnp.broadcast_to(opacities[None, :], z.shape)).astype(z.dtype)
    sxx = jax.lax.stop_gradient(cxx)
    syy = jax.lax.stop_gradient(cyy)
    visible = op >= ALPHA_MIN
    extend = jnp.minimum(jnp.sqrt(2.0 * jnp.log(jnp.maximum(op / ALPHA_MIN, 1.0))), EXTEND_MAX)
    half = jnp.stack([extend * jnp.sqrt(jnp.maximum(sxx, 0.0)), extend * jnp.sqrt(jnp.maximum(syy, 0.0))], axis=-1)
    half = jnp.minimum(jnp.nan_to_num(half, nan=0.0, posinf=float(2**30), neginf=0.0), float(2**30))
    rad = jnp.ceil(half)
    m2 = jax.lax.stop_gradient(means2d)
    inside = (
        (m2[..., 0] + rad[..., 0] > 0)
        & (m2[..., 0] - rad[..., 0] < width)
        & (m2[..., 1] + rad[..., 1] > 0)
        & (m2[..., 1] - rad[..., 1] < height)
    )
    finite = jnp.all(jnp.isfinite(m2), axis=-1) & jnp.isfinite(sxx) & jnp.isfinite(syy) & jnp.isfinite(cxy)
    valid = in_depth & ok_det & visible & inside & finite & (jnp.max(rad, axis=-1) > 0)
    radii = jnp.where(valid, jnp.max(rad, axis=-1), 0.0).astype(jnp.int32)
    half = jnp.where(valid[..., None], half, 0.0)
    return (means2d, conics, z, colors), (half, radii)


def _segment_add(a: tuple[jax.Array, jax.Array], b: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array]:
    """Combine step of a segmented inclusive sum: a run restarts where b's segment-start flag is set."""
    av, af = a
    bv, bf = b
    return jnp.where(bf, bv, av + bv), af | bf


def _segmented_scan(values: jax.Array, starts: jax.Array) -> jax.Array:
    out, _ = jax.lax.associative_scan(_segment_add, (values, starts))
    return out


@jax.custom_vjp
def segmented_cumsum(values: jax.Array, starts: jax.Array) -> jax.Array:
    """Inclusive cumulative sum of `values` [P] restarting at every True in `starts` [P].

    Its transpose is the same scan run backwards (suffix sums within each segment); writing that down is ~8x faster
    than letting JAX differentiate through the scan's strided slices."""
    return _segmented_scan(values, starts)


def _segmented_cumsum_fwd(values: jax.Array, starts: jax.Array) -> tuple[jax.Array, jax.Array]:
    return _segmented_scan(values, starts), starts


def _segmented_cumsum_bwd(starts: jax.Array, g: jax.Array) -> tuple[jax.Array, None]:
    ends = jnp.concatenate([starts[1:], jnp.ones((1,), dtype=bool)])  # last pair of each segment
    return _segmented_scan(g[::-1], ends[::-1])[::-1], None


segmented_cumsum.defvjp(_segmented_cumsum_fwd, _segmented_cumsum_bwd)


@partial(jax.jit, static_argnames=("num_pixels", "width", "height"))
def composite(
    means2d: jax.Array,  # [M, 2] flattened over (camera, Gaussian)
    conics: jax.Array,  # [M, 3]
    depths: jax.Array,  # [M]
    colors: jax.Array,  # [M, 3]
    opacities: jax.Array,  # [M]
    background: jax.Array,  # [3]
    gauss_idx: jax.Array,  # [P] int32 index into M
    pixel_idx: jax.Array,  # [P] int32 global pixel id (camera * H * W + row * W + col); num_pixels = padding
    starts: jax.Array,  # [P] bool, True at the first pair of each pixel run
    *,
    num_pixels: int,
    width: int,
    height: int,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(rgb [num_pixels, 3], alpha [num_pixels], depth [num_pixels]) over sorted pairs (see module docstring)."""
    dtype = means2d.dtype
    local = pixel_idx % (width * height)
    px = (local % width).astype(dtype) + 0.5
    py = (local // width).astype(dtype) + 0.5
    m = jnp.take(means2d, gauss_idx, axis=0)  # [P, 2]
    q = jnp.take(conics, gauss_idx, axis=0)  # [P, 3]
    o = jnp.take(opacities, gauss_idx, axis=0)  # [P]
    dx = m[:, 0] - px
    dy = m[:, 1] - py
    sigma = 0.5 * (q[:, 0] * dx * dx + q[:, 2] * dy * dy) + q[:, 1] * dx * dy
    alpha = jnp.minimum(ALPHA_MAX, o * jnp.exp(-jnp.maximum(sigma, 0.0)))
    valid = (sigma >= 0) & (alpha >= ALPHA_MIN) & (pixel_idx < num_pixels)
    log_keep = jnp.where(valid, jnp.log1p(-jnp.where(valid, alpha, 0.0)), 0.0)  # [P] log(1 - alpha)
    log_t_incl = segmented_cumsum(log_keep, starts)
    used = valid & (log_t_incl > LOG_T_MIN)
    weight = jnp.where(used, jnp.exp(log_t_incl - log_keep) * alpha, 0.0)  # T * alpha

    seg = partial(jax.ops.segment_sum, segment_ids=pixel_idx, num_segments=num_pixels + 1, indices_are_sorted=True)
    c = jnp.take(colors, gauss_idx, axis=0)  # [P, 3]
    z = jnp.take(depths, gauss_idx, axis=0)  # [P]
    t_final = jnp.exp(seg(jnp.where(used, log_keep, 0.0))[:num_pixels])  # [num_pixels]
    rgb = seg(weight[:, None] * c)[:num_pixels] + t_final[:, None] * background
    depth = seg(weight * z)[:num_pixels]
    return rgb, 1.0 - t_final, depth

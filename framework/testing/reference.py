"""An independent float64 brute-force Gaussian compositor: the ground truth for the rasterizer backends.

Written from the rules in `framework.interfaces.rasterizer` without sharing code with any backend (only the SH
constants are imported): every Gaussian is evaluated at every pixel, with no screen boxes, so a backend whose box
drops a contributing pixel disagrees with it. Gaussians are visited one at a time in depth order while every pixel
keeps its own transmittance and "finished" flag, which is exactly the per-pixel sequential loop run for all pixels
at once. It is differentiable (torch autograd), so small scenes can also check gradients; it is slow by design.
"""

from __future__ import annotations

import torch
from torch import Tensor

from framework.interfaces.rasterizer import (
    ALPHA_MAX,
    ALPHA_MIN,
    EPS2D,
    FAR_PLANE,
    NEAR_PLANE,
    TRANSMITTANCE_MIN,
)
from framework.splat.sh import SH_C0, SH_C1, SH_C2, SH_C3


def _rotation(q: Tensor) -> Tensor:
    """wxyz (any norm, zero -> identity) -> 3x3."""
    n = torch.sqrt((q * q).sum())
    if float(n.detach()) <= 1e-12:
        return torch.eye(3, dtype=q.dtype, device=q.device)
    w, x, y, z = q / n
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]),
        ]
    )


def _sh_colour(degree: int, coeffs: Tensor, d: Tensor) -> Tensor:
    """coeffs [K, 3], direction d [3] (unnormalised) -> rgb [3] = SH + 0.5 clamped at 0."""
    n = torch.sqrt((d * d).sum())
    x, y, z = d / torch.clamp(n, min=1e-12)
    basis = [SH_C0 * torch.ones_like(x)]
    if degree >= 1:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        basis += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2 * z * z - x * x - y * y),
            SH_C2[3] * x * z,
            SH_C2[4] * (x * x - y * y),
        ]
    if degree >= 3:
        basis += [
            SH_C3[0] * y * (3 * x * x - y * y),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4 * z * z - x * x - y * y),
            SH_C3[3] * z * (2 * z * z - 3 * x * x - 3 * y * y),
            SH_C3[4] * x * (4 * z * z - x * x - y * y),
            SH_C3[5] * z * (x * x - y * y),
            SH_C3[6] * x * (x * x - 3 * y * y),
        ]
    rgb = sum(b * coeffs[i] for i, b in enumerate(basis)) + 0.5
    return torch.clamp(rgb, min=0.0)


def _project_one(mean, q, s, K, W2C, width, height):
    """Camera-space z, pixel mean [2] and the dilated 2x2 covariance of one Gaussian."""
    R, t = W2C[:3, :3], W2C[:3, 3]
    pc = R @ mean + t
    x, y, z = pc[0], pc[1], pc[2]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    mean2d = torch.stack([fx * x / z + cx, fy * y / z + cy])
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    u = torch.clamp(x / z, min=float(-(cx / fx + 0.3 * tan_x)), max=float((width - cx) / fx + 0.3 * tan_x))
    v = torch.clamp(y / z, min=float(-(cy / fy + 0.3 * tan_y)), max=float((height - cy) / fy + 0.3 * tan_y))
    zero = torch.zeros_like(z)
    J = torch.stack([torch.stack([fx / z, zero, -fx * u / z]), torch.stack([zero, fy / z, -fy * v / z])])
    Rg = _rotation(q)
    Sigma = Rg @ torch.diag(s * s) @ Rg.T
    cov = J @ R @ Sigma @ R.T @ J.T + EPS2D * torch.eye(2, dtype=mean.dtype, device=mean.device)
    return z, mean2d, cov


def reference_render(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    sh: Tensor,
    K: Tensor,  # [C, 3, 3]
    world_to_cam: Tensor,  # [C, 4, 4]
    width: int,
    height: int,
    sh_degree: int,
    background: Tensor | None = None,
    near: float = NEAR_PLANE,
    far: float = FAR_PLANE,
) -> dict[str, Tensor]:
    """rgb [C,H,W,3], alpha [C,H,W,1], depth [C,H,W,1], means2d [C,N,2] in float64 by brute force."""
    f64 = torch.float64
    means, quats, scales, opacities, sh = (x.to(f64) for x in (means, quats, scales, opacities, sh))
    K, world_to_cam = K.to(f64), world_to_cam.to(f64)
    bg = torch.zeros(3, dtype=f64) if background is None else background.to(f64)
    jj, ii = torch.meshgrid(torch.arange(width, dtype=f64), torch.arange(height, dtype=f64), indexing="xy")
    px, py = jj + 0.5, ii + 0.5  # [H, W] pixel centres
    rgbs, alphas, depths, m2ds = [], [], [], []
    for c in range(K.shape[0]):
        W2C = world_to_cam[c]
        centre = -W2C[:3, :3].T @ W2C[:3, 3]
        items = []
        m2d_c = []
        for g in range(means.shape[0]):
            z, m2d, cov = _project_one(means[g], quats[g], scales[g], K[c], W2C, width, height)
            m2d_c.append(m2d)
            if not (near < float(z.detach()) < far):
                continue
            det = cov[0, 0] * cov[1, 1] - cov[0, 1] * cov[1, 0]
            if float(det.detach()) <= 0:
                continue
            conic = torch.stack([cov[1, 1], -cov[0, 1], cov[0, 0]]) / det
            colour = _sh_colour(sh_degree, sh[g], means[g] - centre)
            items.append((float(z.detach()), g, z, m2d, conic, colour))
        items.sort(key=lambda it: (it[0], it[1]))  # front to back; ties by index
        T = torch.ones(height, width, dtype=f64)
        done = torch.zeros(height, width, dtype=torch.bool)
        rgb = torch.zeros(height, width, 3, dtype=f64)
        dep = torch.zeros(height, width, dtype=f64)
        for _, g, z, m2d, conic, colour in items:
            dx, dy = m2d[0] - px, m2d[1] - py
            sigma = 0.5 * (conic[0] * dx * dx + conic[2] * dy * dy) + conic[1] * dx * dy
            alpha = torch.clamp(opacities[g] * torch.exp(-sigma), max=ALPHA_MAX)
            hit = (sigma >= 0) & (alpha >= ALPHA_MIN) & ~done
            next_T = T * (1 - alpha)
            finish = hit & (next_T <= TRANSMITTANCE_MIN)
            add = hit & ~finish
            wgt = torch.where(add, T * alpha, torch.zeros_like(T))
            rgb = rgb + wgt[..., None] * colour
            dep = dep + wgt * z
            T = torch.where(add, next_T, T)
            done = done | finish
        rgbs.append(rgb + T[..., None] * bg)
        alphas.append((1 - T)[..., None])
        depths.append(dep[..., None])
        m2ds.append(torch.stack(m2d_c) if m2d_c else torch.zeros(0, 2, dtype=f64))
    return {
        "rgb": torch.stack(rgbs),
        "alpha": torch.stack(alphas),
        "depth": torch.stack(depths),
        "means2d": torch.stack(m2ds),
    }

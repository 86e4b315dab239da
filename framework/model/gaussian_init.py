"""Initial canonical Gaussians: on a body's rest surface (avatars) or in a box / at given points (static scenes).

Why these choices:
- Surface samples are area-weighted so density is uniform over the skin; the scale is the local sample spacing
  (root-mean-square distance to the k nearest samples, as 3DGS does for its SfM points) so neighbours overlap without
  leaving holes.
- Surface Gaussians are flattened along the face normal (thin axis = local z) because skin is a surface: a flat disc
  renders the silhouette correctly from the start, and the optimiser thickens it where needed.
- The 9-dim latent code starts as the 1-frequency positional encoding of the box-normalised position, so nearby
  Gaussians start with similar codes (the corrector then generalises spatially) while distinct places differ.
- Only the DC SH term is set (a grey or given colour); higher degrees start at zero and are switched on progressively.
All functions return plain float32 tensors in a `Gaussians`; the module that trains them wraps them in parameters.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from framework.geometry import rotmat_to_quat
from framework.model.posenc import normalize_to_bounds, posenc
from framework.splat.sh import rgb_to_sh0
from framework.types import Gaussians, num_sh_coeffs


def _as_np(x) -> np.ndarray:
    if isinstance(x, Tensor):
        return x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=np.float64)


def knn_spacing(points: np.ndarray, k: int = 3) -> np.ndarray:
    """Root-mean-square distance of each point [M, 3] to its k nearest other points -> [M] (>= 1e-7)."""
    from scipy.spatial import cKDTree

    m = points.shape[0]
    if m < 2:
        return np.full((m,), 1e-2)
    k = min(k, m - 1)
    dist, _ = cKDTree(points).query(points, k=k + 1)  # first neighbour is the point itself
    dist = dist.reshape(m, k + 1)[:, 1:]
    return np.sqrt((dist**2).mean(axis=1)).clip(min=1e-7)


def sample_surface(vertices, faces, num: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Area-weighted uniform samples on a triangle mesh.

    Returns points [num, 3], face index [num], barycentric coordinates [num, 3] (deterministic for a seed).
    """
    v = _as_np(vertices)
    f = np.asarray(faces.detach().cpu().numpy() if isinstance(faces, Tensor) else faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise ValueError(f"sample_surface: faces must be [F, 3] with F > 0, got shape {f.shape}.")
    tri = v[f]  # [F, 3, 3]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not area.sum() > 0:
        raise ValueError("sample_surface: the mesh has zero total area; check rest_vertices / faces.")
    rng = np.random.default_rng(seed)
    face = rng.choice(f.shape[0], size=num, p=area / area.sum())
    r1, r2 = rng.random(num), rng.random(num)
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)  # uniform on the triangle
    points = (bary[:, :, None] * tri[face]).sum(1)
    return points, face, bary


def _frames_from_normals(n: np.ndarray) -> np.ndarray:
    """Right-handed rotations [M, 3, 3] whose third column is the unit normal n [M, 3]."""
    n = n / np.linalg.norm(n, axis=1, keepdims=True).clip(min=1e-12)
    helper = np.zeros_like(n)
    use_y = np.abs(n[:, 0]) > 0.9
    helper[~use_y, 0] = 1.0
    helper[use_y, 1] = 1.0
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True).clip(min=1e-12)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2, n], axis=2)  # columns t1, t2, n; det = +1


def _appearance(num: int, sh_degree: int, color, opacity: float, colors: np.ndarray | None = None):
    if not 0.0 < opacity < 1.0:
        raise ValueError(f"gaussians.opacity: expected a value in (0, 1), got {opacity}.")
    if not 0 <= sh_degree <= 3:
        raise ValueError(f"gaussians.sh_degree: expected 0..3, got {sh_degree}.")
    sh = torch.zeros(num, num_sh_coeffs(sh_degree), 3)
    rgb_np = np.array(colors if colors is not None else np.broadcast_to(np.asarray(color, float), (num, 3)))
    rgb = torch.as_tensor(rgb_np)
    sh[:, 0] = rgb_to_sh0(rgb.float().reshape(num, 3))
    logit = float(np.log(opacity / (1 - opacity)))
    return sh, torch.full((num,), logit)


def _latents(points: np.ndarray, bounds) -> Tensor:
    x = torch.as_tensor(points, dtype=torch.float64)
    return posenc(normalize_to_bounds(x, None if bounds is None else torch.as_tensor(bounds).double()), 1).float()


def from_mesh_surface(
    vertices,
    faces,
    num: int,
    sh_degree: int = 3,
    seed: int = 0,
    opacity: float = 0.1,
    color=(0.5, 0.5, 0.5),
    bounds=None,
    knn: int = 3,
    flatten: float = 0.1,
) -> Gaussians:
    """Gaussians on a mesh surface [V, 3] / [F, 3]: flat discs (thin axis along the face normal, `flatten` times
    the in-plane scale) sized by local spacing. `bounds` [2, 3] normalises positions for the latent codes
    (default: the mesh's bounding box)."""
    if num <= 0:
        raise ValueError(f"gaussians.num: expected a positive count, got {num}.")
    v = _as_np(vertices)
    points, face, _ = sample_surface(v, faces, num, seed)
    f = np.asarray(faces.detach().cpu().numpy() if isinstance(faces, Tensor) else faces, dtype=np.int64)
    tri = v[f[face]]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    rot = _frames_from_normals(normals)
    spacing = knn_spacing(points, knn)
    log_scales = np.log(np.stack([spacing, spacing, spacing * flatten], axis=1))
    if bounds is None:
        bounds = np.stack([v.min(0), v.max(0)])
    sh, opacity_logits = _appearance(num, sh_degree, color, opacity)
    return Gaussians(
        means=torch.as_tensor(points, dtype=torch.float32),
        quats=rotmat_to_quat(torch.as_tensor(rot)).float(),
        log_scales=torch.as_tensor(log_scales, dtype=torch.float32),
        opacity_logits=opacity_logits,
        sh=sh,
        latents=_latents(points, bounds),
        skin_weights=None,
    )


def from_body_surface(body, num: int, sh_degree: int = 3, seed: int = 0, opacity: float = 0.1, **kwargs) -> Gaussians:
    """Gaussians on the rest surface of a `BodyModel` (its `rest_vertices` / `faces`); see `from_mesh_surface`."""
    return from_mesh_surface(body.rest_vertices, body.faces, num, sh_degree, seed, opacity, **kwargs)


def from_points(
    points,
    sh_degree: int = 3,
    opacity: float = 0.1,
    colors=None,
    color=(0.5, 0.5, 0.5),
    bounds=None,
    knn: int = 3,
) -> Gaussians:
    """Isotropic Gaussians at given points [M, 3] (e.g. a dataset's initial points), sized by local spacing;
    `colors` [M, 3] in [0, 1] or one grey `color`."""
    p = _as_np(points).reshape(-1, 3)
    num = p.shape[0]
    if num == 0:
        raise ValueError("gaussian init: no points given; pass at least one point or use random_in_box.")
    spacing = knn_spacing(p, knn)
    if bounds is None:
        bounds = np.stack([p.min(0), p.max(0)])
    sh, opacity_logits = _appearance(num, sh_degree, color, opacity, None if colors is None else _as_np(colors))
    quats = torch.zeros(num, 4)
    quats[:, 0] = 1.0
    return Gaussians(
        means=torch.as_tensor(p, dtype=torch.float32),
        quats=quats,
        log_scales=torch.as_tensor(np.log(spacing), dtype=torch.float32)[:, None].repeat(1, 3),
        opacity_logits=opacity_logits,
        sh=sh,
        latents=_latents(p, bounds),
        skin_weights=None,
    )


def random_in_box(bounds, num: int, sh_degree: int = 3, seed: int = 0, opacity: float = 0.1, **kwargs) -> Gaussians:
    """`num` isotropic Gaussians uniformly in the box `bounds` [2, 3] (static scenes without initial points)."""
    b = _as_np(bounds)
    if b.shape != (2, 3) or not np.all(b[1] > b[0]):
        raise ValueError(
            f"gaussian init: bounds must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max > min, got {b.tolist()}."
        )
    if num <= 0:
        raise ValueError(f"gaussians.num: expected a positive count, got {num}.")
    rng = np.random.default_rng(seed)
    points = b[0] + rng.random((num, 3)) * (b[1] - b[0])
    return from_points(points, sh_degree=sh_degree, opacity=opacity, bounds=b, **kwargs)

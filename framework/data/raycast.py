"""Ground-truth renderer: ray casting a triangle mesh with Embree (through embreex), independent of any rasterizer.

Why a separate renderer: the data our Gaussians are fitted to must not come from the code under test. Ray casting
gives exact visibility, per-pixel triangle ids and barycentric coordinates (so any surface attribute — UV texture,
per-vertex colour, or a procedural texture evaluated on the rest-pose surface — can be looked up), true depth, and
shadow rays for cast shadows, all at ~10-20 M rays/s on CPU.

Conventions (shared with the rasterizers, see `framework.types`):
- Cameras are pinhole, `K` [3, 3] in pixels, `world_to_cam` [4, 4] OpenCV (x right, y down, z forward).
- Pixel (row i, column j) has its centre at image coordinates (j + 0.5, i + 0.5).
- The background is black: missed rays contribute colour 0.
- Depth is camera-space z (not ray length); 0 where nothing was hit.
- Barycentrics are the weights of the triangle's three corners, in `faces[f]` order (they sum to 1).
- Supersampling (`supersample = s`): s x s stratified rays per pixel at offsets ((a + 0.5) / s, (b + 0.5) / s);
  `rgb` is the mean of the sub-samples (anti-aliased edges against black), `coverage` is the fraction of sub-samples
  that hit, and `mask` is the majority vote `coverage >= 0.5`. Face ids, barycentrics and depth always come from the
  pixel-centre ray (one extra ray per pixel when s is even), so they stay exact surface lookups.
- Textures: `uv` (0, 0) is the bottom-left of the texture image (OBJ/MakeHuman convention), so texel row
  = (1 - v) * H_tex; sampling is bilinear with wrap-around.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: Colour callback: (face_ids [N], barycentrics [N, 3], hit points [N, 3] world) -> colours [N, 3] float in [0, 1].
ColorFn = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]

_render_calls = 0  # incremented by `render`; lets callers (tests) prove that a cache was reused


def render_call_count() -> int:
    """How many images `render` has produced in this process."""
    return _render_calls


@dataclass
class Camera:
    """One pinhole camera (float64 numpy, OpenCV)."""

    K: np.ndarray  # [3, 3]
    world_to_cam: np.ndarray  # [4, 4]
    width: int
    height: int

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.world_to_cam = np.asarray(self.world_to_cam, dtype=np.float64).reshape(4, 4)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"Camera: width/height must be positive, got {self.width}x{self.height}.")

    @property
    def center(self) -> np.ndarray:
        R, t = self.world_to_cam[:3, :3], self.world_to_cam[:3, 3]
        return -R.T @ t  # [3]

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points [N, 3] -> (pixel coordinates [N, 2] as (x, y) with centres at +0.5, camera z [N])."""
        cam = points @ self.world_to_cam[:3, :3].T + self.world_to_cam[:3, 3]  # [N, 3]
        z = cam[:, 2]
        uvw = cam @ self.K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = uvw[:, :2] / uvw[:, 2:3]
        return xy, z


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """OpenCV world-to-camera [4, 4] of a camera at `eye` looking at `target` with `up` pointing up in the image."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along `up`: pick any perpendicular
        x = np.cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # image y points down
    R = np.stack([x, y, z])  # rows: camera axes in world
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c


def intrinsics(fov_deg: float, width: int, height: int) -> np.ndarray:
    """K [3, 3] for a horizontal field of view, principal point at the image centre."""
    f = 0.5 * width / np.tan(np.deg2rad(fov_deg) / 2)
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=np.float64)


def camera_rays(cam: Camera, offsets: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rays through pixel sub-positions.

    offsets [S, 2] (x, y) inside the pixel, default [[0.5, 0.5]] (the centre). Returns origins [H*W*S, 3] and
    directions [H*W*S, 3] ordered (row, column, sample), float32. Directions are scaled so their camera-space z is 1:
    the ray parameter t of a hit is then its camera depth.
    """
    if offsets is None:
        offsets = np.array([[0.5, 0.5]])
    H, W = cam.height, cam.width
    px = (np.arange(W, dtype=np.float64)[None, :, None] + offsets[None, None, :, 0]).reshape(1, W, -1)  # [1, W, S]
    py = (np.arange(H, dtype=np.float64)[:, None, None] + offsets[None, None, :, 1]).reshape(H, 1, -1)  # [H, 1, S]
    # world direction = R^T K^-1 (px, py, 1): a 3x3 map applied component-wise (matmul on [N, 3] is slow)
    M = cam.world_to_cam[:3, :3].T @ np.linalg.inv(cam.K)  # [3, 3]
    d_world = np.empty((H, W, px.shape[-1], 3), dtype=np.float32)
    for c in range(3):
        d_world[..., c] = M[c, 0] * px + M[c, 1] * py + M[c, 2]
    d_world = d_world.reshape(-1, 3)
    origins = np.empty_like(d_world)
    origins[:] = cam.center.astype(np.float32)
    return origins, d_world


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals [V, 3] (zero-area neighbourhoods get +z)."""
    v = np.asarray(vertices, dtype=np.float64)
    fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])  # [F, 3], |fn| = 2 area
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    out = np.where(norm > 1e-20, vn / np.maximum(norm, 1e-20), np.array([0.0, 0.0, 1.0]))
    return out


class RayCaster:
    """An Embree scene of one triangle mesh: first hits (triangle id, barycentrics, distance) and occlusion tests."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        vertices = np.asarray(vertices, dtype=np.float64)
        faces = np.asarray(faces, dtype=np.int64)
        if vertices.ndim != 2 or vertices.shape[1] != 3:
            raise ValueError(f"RayCaster: vertices must be [V, 3], got {vertices.shape}.")
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"RayCaster: faces must be [F, 3], got {faces.shape}.")
        if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
            raise ValueError(
                f"RayCaster: face indices must lie in [0, {len(vertices)}), found {faces.min()}..{faces.max()}."
            )
        if not np.isfinite(vertices).all():
            raise ValueError("RayCaster: vertices contain NaN/inf; check the mesh or the pose that produced it.")
        self.vertices = vertices
        self.faces = faces
        self._scene = rtcore_scene.EmbreeScene()
        self._empty = len(faces) == 0
        if not self._empty:
            TriangleMesh(self._scene, vertices.astype(np.float32)[faces])

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First hits: face ids [N] (-1 = miss), barycentrics [N, 3] (corner weights), t [N] (in direction units)."""
        n = len(origins)
        if self._empty or n == 0:
            return np.full(n, -1, np.int64), np.zeros((n, 3), np.float32), np.zeros(n, np.float32)
        out = self._scene.run(
            np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(directions, np.float32), output=1
        )
        fid = out["primID"].astype(np.int64)
        hit = (out["geomID"] >= 0) & (fid >= 0)
        fid = np.where(hit, fid, -1)
        u, v = out["u"], out["v"]  # Embree: p = (1 - u - v) p0 + u p1 + v p2
        bary = np.stack([1.0 - u - v, u, v], axis=1).astype(np.float32)
        bary[~hit] = 0.0
        t = np.where(hit, out["tfar"], 0.0).astype(np.float32)
        return fid, bary, t

    def occluded(self, origins: np.ndarray, directions: np.ndarray, max_t: np.ndarray | float = 1e30) -> np.ndarray:
        """bool [N]: does the segment origin + t * direction, 0 < t < max_t, hit any triangle?"""
        n = len(origins)
        if self._empty or n == 0:
            return np.zeros(n, bool)
        dists = np.broadcast_to(np.asarray(max_t, np.float32), (n,)).copy()
        res = self._scene.run(
            np.ascontiguousarray(origins, np.float32),
            np.ascontiguousarray(directions, np.float32),
            dists=dists,
            query="OCCLUDED",
        )
        return np.asarray(res) != -1


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup with wrap-around. texture [Ht, Wt, 3] (uint8 or float in [0, 1]), uv [N, 2] -> [N, 3] float."""
    tex = texture.astype(np.float32) / 255.0 if texture.dtype == np.uint8 else texture.astype(np.float32)
    Ht, Wt = tex.shape[:2]
    x = uv[:, 0] * Wt - 0.5
    y = (1.0 - uv[:, 1]) * Ht - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0i, y0i = x0.astype(np.int64) % Wt, y0.astype(np.int64) % Ht
    x1i, y1i = (x0i + 1) % Wt, (y0i + 1) % Ht
    top = tex[y0i, x0i] * (1 - fx) + tex[y0i, x1i] * fx
    bot = tex[y1i, x0i] * (1 - fx) + tex[y1i, x1i] * fx
    return top * (1 - fy) + bot * fy


@dataclass
class Shading:
    """Lambertian shading with one directional light: colour * (ambient + diffuse * max(0, n.l) * visible), plus an
    optional white Blinn-Phong highlight specular * max(0, n.h)^shininess * visible (h halfway between the light and
    the viewer): the one view-dependent term, for glossy cloth.

    `direction` points from the surface towards the light. `shadows` casts a shadow ray per shaded sample, so the
    mesh darkens itself where it blocks the light (used for pose-dependent self-shadows).
    """

    direction: tuple[float, float, float] = (0.4, -0.5, 0.75)
    ambient: float = 0.35
    diffuse: float = 0.75
    shadows: bool = False
    smooth_normals: bool = True
    shadow_bias: float = 1e-3  # ray offset along the normal, in scene units
    specular: float = 0.0  # 0: matte (view-independent)
    shininess: float = 16.0


@dataclass
class RenderResult:
    rgb: np.ndarray  # [H, W, 3] uint8
    mask: np.ndarray  # [H, W] bool (majority of sub-samples hit)
    coverage: np.ndarray  # [H, W] float32 fraction of sub-samples that hit
    depth: np.ndarray  # [H, W] float32 camera z of the centre ray, 0 = miss
    face_ids: np.ndarray  # [H, W] int64 of the centre ray, -1 = miss
    bary: np.ndarray  # [H, W, 3] float32 of the centre ray
    rgb_float: np.ndarray  # [H, W, 3] float32 in [0, 1] before quantisation


def _subpixel_offsets(s: int) -> np.ndarray:
    g = (np.arange(s) + 0.5) / s
    xx, yy = np.meshgrid(g, g)
    return np.stack([xx.ravel(), yy.ravel()], axis=1)  # [s*s, 2]


def render(
    vertices: np.ndarray,
    faces: np.ndarray,
    camera: Camera,
    *,
    texture: np.ndarray | None = None,
    uvs: np.ndarray | None = None,
    face_uvs: np.ndarray | None = None,
    vertex_colors: np.ndarray | None = None,
    color_fn: ColorFn | None = None,
    shading: Shading | None = None,
    normals: np.ndarray | None = None,
    supersample: int = 1,
    caster: RayCaster | None = None,
) -> RenderResult:
    """Ray-cast one image of a mesh.

    Colour source, first that is given: `color_fn(face_ids, bary, points)`; `texture` with `uvs` [Vt, 2] and
    `face_uvs` [F, 3]; `vertex_colors` [V, 3] interpolated; else white. `shading=None` renders the unlit colour.
    `normals` [V, 3] overrides the shading normals (e.g. flat boxes next to smooth spheres in one mesh).
    Pass a prebuilt `caster` to reuse one Embree scene for several cameras (it must hold the same mesh).
    """
    global _render_calls
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if supersample < 1:
        raise ValueError(f"render: supersample must be >= 1, got {supersample}.")
    if texture is not None and (uvs is None or face_uvs is None):
        raise ValueError("render: a texture needs `uvs` [Vt, 2] and `face_uvs` [F, 3]; pass both or use color_fn.")
    if face_uvs is not None and len(face_uvs) != len(faces):
        raise ValueError(f"render: face_uvs has {len(face_uvs)} rows, expected one per face ({len(faces)}).")
    if vertex_colors is not None and len(vertex_colors) != len(vertices):
        raise ValueError(f"render: vertex_colors has {len(vertex_colors)} rows, expected {len(vertices)}.")
    caster = caster or RayCaster(vertices, faces)
    H, W = camera.height, camera.width
    vn = None
    if normals is not None:
        if np.shape(normals) != vertices.shape:
            raise ValueError(f"render: normals must be [V, 3] = {vertices.shape}, got {np.shape(normals)}.")
        vn = np.asarray(normals, dtype=np.float64)
    elif shading is not None and shading.smooth_normals:
        vn = vertex_normals(vertices, faces)

    def shade(fid: np.ndarray, bary: np.ndarray, t: np.ndarray, org: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        hit = fid >= 0
        col = np.zeros((len(fid), 3), np.float32)
        if not hit.any():
            return col
        f, b = fid[hit], bary[hit].astype(np.float64)
        tri = vertices[faces[f]]  # [N, 3, 3]
        pts = np.einsum("nk,nkc->nc", b, tri)  # [N, 3]
        if color_fn is not None:
            c = np.asarray(color_fn(f, b.astype(np.float32), pts.astype(np.float32)), dtype=np.float32)
        elif texture is not None:
            uv = np.einsum("nk,nkc->nc", b, np.asarray(uvs, np.float64)[np.asarray(face_uvs)[f]])
            c = sample_texture(texture, uv)
        elif vertex_colors is not None:
            vc = np.asarray(vertex_colors, np.float32)
            vc = vc / 255.0 if np.asarray(vertex_colors).dtype == np.uint8 else vc
            c = np.einsum("nk,nkc->nc", b, vc[faces[f]]).astype(np.float32)
        else:
            c = np.ones((len(f), 3), np.float32)
        if shading is not None:
            fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-20)
            n = np.einsum("nk,nkc->nc", b, vn[faces[f]]) if vn is not None else fn
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)
            # two-sided: the normal faces the viewer
            flip = np.einsum("nc,nc->n", fn, dirs[hit]) > 0
            n[flip] *= -1
            fn[flip] *= -1
            light = np.asarray(shading.direction, np.float64)
            light = light / np.linalg.norm(light)
            ndl = np.clip(n @ light, 0.0, None)
            vis = np.ones(len(ndl))
            if shading.shadows:
                lit = ndl > 0
                if lit.any():
                    o = pts[lit] + shading.shadow_bias * fn[lit]
                    occ = caster.occluded(o, np.broadcast_to(light, o.shape))
                    vis[np.flatnonzero(lit)[occ]] = 0.0
                    ndl = ndl * vis
            c = c * (shading.ambient + shading.diffuse * ndl)[:, None]
            if shading.specular > 0:
                view = -dirs[hit] / np.linalg.norm(dirs[hit], axis=1, keepdims=True)  # towards the camera
                half = view + light
                half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-20)
                ndh = np.clip(np.einsum("nc,nc->n", n, half), 0.0, None) * (ndl > 0)
                c = c + (shading.specular * ndh**shading.shininess)[:, None]
        col[hit] = np.clip(c, 0.0, 1.0)
        return col

    # centre rays: exact surface lookups (and the colour when not supersampling)
    org, dirs = camera_rays(camera)
    fid, bary, t = caster.intersect(org, dirs)
    if supersample == 1:
        rgb = shade(fid, bary, t, org, dirs).reshape(H, W, 3)
        coverage = (fid >= 0).astype(np.float32).reshape(H, W)
    else:
        S = supersample * supersample
        org_s, dirs_s = camera_rays(camera, _subpixel_offsets(supersample))
        fid_s, bary_s, t_s = caster.intersect(org_s, dirs_s)
        rgb = shade(fid_s, bary_s, t_s, org_s, dirs_s).reshape(H, W, S, 3).mean(axis=2)
        coverage = (fid_s >= 0).reshape(H, W, S).mean(axis=2).astype(np.float32)
    _render_calls += 1
    rgb = rgb.astype(np.float32)
    return RenderResult(
        rgb=np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8),
        mask=coverage >= 0.5,
        coverage=coverage,
        depth=t.reshape(H, W),
        face_ids=fid.reshape(H, W),
        bary=bary.reshape(H, W, 3),
        rgb_float=rgb,
    )

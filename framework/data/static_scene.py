"""A small procedurally textured mesh scene, ray-cast from a ring of cameras: the target of `static_fit`.

Why this scene: a static multi-view Gaussian fit needs images with known cameras that a random-init fit of ~10-20k
Gaussians can reproduce well in a few CPU minutes. So the scene is a handful of smooth primitives (box, sphere,
torus, capsule) with solid (3D procedural) textures of moderate frequency — colour gradients, soft checkers and soft
stripes with periods of ~0.3-0.6 scene units (tens of pixels at 128 px) — and view-independent Lambertian shading
without cast shadows. Nothing is finer than a few pixels, so PSNR on held-out views measures the fit, not aliasing.

The images are rendered by `framework.data.raycast` (Embree), never by our Gaussian rasterizer, and cached under
`framework.paths.data_dir()/static_scene/<hash of the settings>/`:
  images/NNN.png (RGB), masks/NNN.png (0/255, majority of 2x2 sub-samples), cameras.json
(`cameras.json` is written last, after the directory is moved into place, so a half-written cache is never read).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from framework.data import raycast

SCENE_VERSION = 1  # bump when the scene or the file layout changes: it invalidates every cache


@dataclass(frozen=True)
class StaticSceneSettings:
    resolution: int = 128
    num_train_views: int = 24
    num_test_views: int = 6
    seed: int = 0
    supersample: int = 2
    camera_radius: float = 4.0
    fov_deg: float = 34.0

    def key(self) -> str:
        blob = json.dumps({"version": SCENE_VERSION, **asdict(self)}, sort_keys=True)
        return hashlib.sha1(blob.encode()).hexdigest()[:12]


@dataclass
class SceneMesh:
    vertices: np.ndarray  # [V, 3] float64
    faces: np.ndarray  # [F, 3] int64
    normals: np.ndarray  # [V, 3] shading normals
    part: np.ndarray  # [F] int64 primitive id of each face
    colors: np.ndarray  # [P, 2, 3] two base colours per primitive

    def color_fn(self, face_ids: np.ndarray, bary: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Solid textures evaluated at the world-space hit point, one pattern per primitive."""
        p = points.astype(np.float64)  # [N, 3]
        part = self.part[face_ids]
        c0, c1 = self.colors[part, 0], self.colors[part, 1]  # [N, 3]
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        w = np.zeros(len(p))
        # 0 box: soft 3D checker, period 0.5
        k = 2 * np.pi / 0.5
        checker = np.sin(k * x + 0.3) * np.sin(k * y + 0.7) * np.sin(k * z + 1.1)
        w = np.where(part == 0, 0.5 + 0.5 * np.tanh(4.0 * checker), w)
        # 1 sphere: vertical gradient plus soft latitude stripes
        w = np.where(part == 1, np.clip(0.5 + 0.35 * np.sin(2 * np.pi * z / 0.35) + 0.3 * (z - 0.0), 0, 1), w)
        # 2 torus: smooth gradient around its ring
        w = np.where(part == 2, 0.5 + 0.5 * np.sin(np.arctan2(y - 0.55, x) * 3.0), w)
        # 3 capsule: soft diagonal stripes
        w = np.where(part == 3, 0.5 + 0.5 * np.tanh(2.5 * np.sin(2 * np.pi * (z + 0.5 * x) / 0.4)), w)
        col = c0 * (1 - w[:, None]) + c1 * w[:, None]
        return col.astype(np.float32)


def build_scene(seed: int) -> SceneMesh:
    """Four primitives inside about [-1.1, 1.1]^3 (z up), with seed-dependent placement jitter and colours."""
    import trimesh

    rng = np.random.default_rng(seed)
    jitter = rng.uniform(-0.08, 0.08, size=(4, 3))
    ang = rng.uniform(0, np.pi / 2)

    box = trimesh.creation.box(extents=(0.75, 0.75, 0.75))
    box = trimesh.Trimesh(
        box.vertices[box.faces].reshape(-1, 3), np.arange(len(box.faces) * 3).reshape(-1, 3), process=False
    )  # unshared corners: flat shading
    rot = trimesh.transformations.rotation_matrix(ang, [0, 0, 1])
    box.apply_transform(rot)
    box.apply_translation(np.array([-0.55, -0.35, -0.45]) + jitter[0])

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.45)
    sphere.apply_translation(np.array([0.5, -0.3, -0.3]) + jitter[1])

    torus = trimesh.creation.torus(major_radius=0.38, minor_radius=0.13, major_sections=64, minor_sections=24)
    torus.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2 - 0.3, [1, 0, 0]))
    torus.apply_translation(np.array([0.0, 0.55, 0.35]) + jitter[2])

    capsule = trimesh.creation.capsule(height=0.9, radius=0.2, count=[32, 32])
    capsule.apply_translation(np.array([-0.45, 0.35, -0.1]) + jitter[3])

    parts = [box, sphere, torus, capsule]
    verts, faces, normals, part = [], [], [], []
    offset = 0
    for i, m in enumerate(parts):
        verts.append(np.asarray(m.vertices, np.float64))
        faces.append(np.asarray(m.faces, np.int64) + offset)
        normals.append(raycast.vertex_normals(np.asarray(m.vertices), np.asarray(m.faces)))
        part.append(np.full(len(m.faces), i, np.int64))
        offset += len(m.vertices)
    palette = np.array(
        [
            [0.85, 0.25, 0.2],
            [0.95, 0.8, 0.3],
            [0.2, 0.45, 0.85],
            [0.25, 0.7, 0.35],
            [0.9, 0.55, 0.75],
            [0.95, 0.95, 0.9],
            [0.3, 0.25, 0.55],
            [0.1, 0.6, 0.65],
        ]
    )
    colors = np.stack([palette[rng.choice(len(palette), 2, replace=False)] for _ in parts])  # [P, 2, 3]
    return SceneMesh(
        np.concatenate(verts), np.concatenate(faces), np.concatenate(normals), np.concatenate(part), colors
    )


def ring_cameras(settings: StaticSceneSettings) -> tuple[list[raycast.Camera], list[str]]:
    """Train and held-out cameras on one spiral over the upper hemisphere (elevation -10..60 degrees) looking at the
    origin; held-out views are evenly spaced along the spiral, so they lie between training views (disjoint)."""
    n_train, n_test = settings.num_train_views, settings.num_test_views
    if n_train < 1 or n_test < 0:
        raise ValueError(f"static_scene: need num_train_views >= 1 and num_test_views >= 0, got {n_train}, {n_test}.")
    n = n_train + n_test
    rng = np.random.default_rng(settings.seed + 1)
    az0 = rng.uniform(0, 2 * np.pi)
    golden = np.pi * (3 - np.sqrt(5))
    test_idx = set((np.arange(n_test) * n) // max(n_test, 1) + n // (2 * max(n_test, 1))) if n_test else set()
    K = raycast.intrinsics(settings.fov_deg, settings.resolution, settings.resolution)
    cams, splits = [], []
    for i in range(n):
        elev = np.deg2rad(-10 + 70 * (i + 0.5) / n)
        az = az0 + golden * i
        r = settings.camera_radius
        eye = r * np.array([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)])
        cams.append(raycast.Camera(K, raycast.look_at(eye, np.zeros(3)), settings.resolution, settings.resolution))
        splits.append("test" if i in test_idx else "train")
    return cams, splits


def render_scene(settings: StaticSceneSettings, out_dir: Path) -> None:
    """Render every view into `out_dir` (images/, masks/, cameras.json)."""
    from PIL import Image

    scene = build_scene(settings.seed)
    cams, splits = ring_cameras(settings)
    caster = raycast.RayCaster(scene.vertices, scene.faces)
    shading = raycast.Shading(direction=(0.35, -0.45, 0.8), ambient=0.45, diffuse=0.6, shadows=False)
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    (out_dir / "masks").mkdir(parents=True, exist_ok=True)
    for i, cam in enumerate(cams):
        res = raycast.render(
            scene.vertices,
            scene.faces,
            cam,
            color_fn=scene.color_fn,
            shading=shading,
            normals=scene.normals,
            supersample=settings.supersample,
            caster=caster,
        )
        Image.fromarray(res.rgb).save(out_dir / "images" / f"{i:03d}.png")
        Image.fromarray((res.mask * 255).astype(np.uint8)).save(out_dir / "masks" / f"{i:03d}.png")
    lo, hi = scene.vertices.min(0), scene.vertices.max(0)
    margin = 0.05 * (hi - lo)
    meta = {
        "version": SCENE_VERSION,
        "settings": asdict(settings),
        "width": settings.resolution,
        "height": settings.resolution,
        "bounds": [(lo - margin).tolist(), (hi + margin).tolist()],
        "cameras": [
            {"name": f"{i:03d}", "split": s, "K": c.K.tolist(), "world_to_cam": c.world_to_cam.tolist()}
            for i, (c, s) in enumerate(zip(cams, splits, strict=True))
        ],
    }
    (out_dir / "cameras.json").write_text(json.dumps(meta, indent=1))


def ensure_static_scene(settings: StaticSceneSettings, root: str | Path | None = None) -> Path:
    """The directory holding the rendered scene; renders it first if it is not there (cached by settings hash).

    `root=None` uses `data_dir()/static_scene/<hash>`; an explicit `root` is used as it is (rendered there when it
    holds no cameras.json). Rendering goes to a temporary sibling that is renamed into place, so concurrent runs
    never see a half-written scene.
    """
    from framework.paths import data_dir

    target = Path(root) if root is not None else data_dir() / "static_scene" / settings.key()
    if (target / "cameras.json").is_file():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))
    try:
        render_scene(settings, tmp)
        if (target / "cameras.json").is_file():  # another process finished first
            return target
        if target.exists():  # an empty or partial directory (e.g. an explicit root): fill it
            for item in sorted(tmp.iterdir(), key=lambda x: x.name == "cameras.json"):  # cameras.json last
                dest = target / item.name
                if dest.is_dir():
                    shutil.rmtree(dest)
                os.replace(item, dest)
        else:
            os.replace(tmp, target)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return target


def load_meta(path: Path) -> dict:
    """cameras.json of a rendered scene, with a clear error when it is missing."""
    f = Path(path) / "cameras.json"
    if not f.is_file():
        raise FileNotFoundError(
            f"static_scene: {f} not found. Expected a scene rendered by framework.data.static_scene; "
            f"pass root=None to render one into the cache."
        )
    return json.loads(f.read_text())

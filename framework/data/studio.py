"""The synthetic studio: a multi-view video of a posed, clothed body, ray-cast and written in the ZJU-MoCap layout.

    python -m framework.data.studio --out DIR --resolution 512 --views 21 --frames 100 --seed 0 --body anny

What it makes (deterministic for the settings; cached by a hash of them, so a second run reuses the sequence, and an
interrupted one resumes: the frames it finished are kept):
- Cameras: a ring of `views` calibrated pinhole cameras at `radius` m around the subject, heights alternating around
  1.3 m, all looking at the body's centre (OpenCV K/R/T, D = 0), like ZJU-MoCap's capture dome.
- Motion (`framework.data.motions`): the anny walk cycle, arm raises, squats and kicks for training, and a held-out
  turn-and-reach motion for novel-pose evaluation; each frame's pose is stored with the body-model name.
- Appearance (`framework.data.appearance`): striped, printed and seamed clothing as a solid texture on the rest-pose
  surface, wrinkle shading that follows joint flexion, and self-shadows from a fixed light (Embree shadow rays).
- Ground truth by ray casting the linear-blend-skinned mesh (`framework.data.raycast`): images, masks, posed
  vertices; `studio.json` next to `annots.npy` records the settings, the motion segments and which frames are the
  novel-pose (held-out) frames.

The subject stands on the floor z = 0 (each frame's Th lifts the lowest posed vertex to 0) and turns with Rh.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import multiprocessing as mp
import os
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from framework.atomic import atomic_write_text
from framework.data import raycast

STUDIO_VERSION = 2
LIGHT = raycast.Shading(direction=(0.45, -0.55, 0.7), ambient=0.32, diffuse=0.78, shadows=True)


@dataclass(frozen=True)
class StudioSettings:
    resolution: int = 512
    views: int = 21
    frames: int = 100
    seed: int = 0
    body: str = "anny"
    skeleton: str = "reduced"  # anny only: "reduced" (22 bones) or "full" (104)
    supersample: int = 1
    radius: float = 3.0
    fov_deg: float = 45.0
    image_ext: str = ".jpg"
    jpeg_quality: int = 95

    def key(self) -> str:
        blob = json.dumps({"version": STUDIO_VERSION, **asdict(self)}, sort_keys=True)
        return hashlib.sha1(blob.encode()).hexdigest()[:12]


def build_body(name: str, skeleton: str = "reduced"):
    """The body model through the registry (anny takes a skeleton option)."""
    from framework import plugins
    from framework.registry import BODIES

    plugins.load_plugins()
    kwargs = {"skeleton": skeleton} if name == "anny" else {}
    return BODIES.build(name, **kwargs)


def camera_ring(settings: StudioSettings, target: np.ndarray) -> list[raycast.Camera]:
    """`views` cameras evenly spaced on a ring (seeded azimuth offset), heights alternating 1.1 / 1.5 m."""
    rng = np.random.default_rng(settings.seed + 7)
    az0 = rng.uniform(0, 2 * np.pi)
    K = raycast.intrinsics(settings.fov_deg, settings.resolution, settings.resolution)
    cams = []
    for i in range(settings.views):
        az = az0 + 2 * np.pi * i / settings.views
        h = 1.1 + 0.4 * (i % 2)
        eye = np.array([settings.radius * np.cos(az), settings.radius * np.sin(az), h])
        cams.append(raycast.Camera(K, raycast.look_at(eye, target), settings.resolution, settings.resolution))
    return cams


# ------------------------------------------------------------------------------------------------ workers
_STATE: dict = {}


def _init_worker(state: dict) -> None:
    _STATE.clear()
    _STATE.update(state)


def _render_frame(f: int) -> int:
    from framework.data.zju.writer import ZjuWriter

    s = _STATE
    verts = s["posed"][f].astype(np.float64)  # [V, 3] world
    faces = s["faces"]
    app = s["appearance"]
    wrinkle = s["wrinkles"][f]  # [V]
    rest = app.rest

    def color(face_ids: np.ndarray, bary: np.ndarray, _points: np.ndarray) -> np.ndarray:
        tri = faces[face_ids]  # [N, 3]
        rest_pts = np.einsum("nk,nkc->nc", bary, rest[tri])
        m = np.einsum("nk,nk->n", bary, wrinkle[tri])
        return app.albedo(face_ids, rest_pts) * m[:, None]

    caster = raycast.RayCaster(verts, faces)
    normals = raycast.vertex_normals(verts, faces)
    imgs, masks = [], []
    for cam in s["cameras"]:
        r = raycast.render(verts, faces, cam, color_fn=color, shading=LIGHT, normals=normals,
                           supersample=s["supersample"], caster=caster)  # fmt: skip
        imgs.append(r.rgb)
        masks.append(r.mask)
    writer = ZjuWriter(s["root"], s["camera_names"], image_ext=s["image_ext"], jpeg_quality=s["jpeg_quality"])
    writer.write_frame(f, np.stack(imgs), np.stack(masks), params=s["params"][f], vertices=s["posed"][f])
    return f


def generate(settings: StudioSettings, out: str | Path | None = None, workers: int = 2, progress: bool = True,
             force: bool = False) -> Path:  # fmt: skip
    """Render the sequence into `out` (default: data_dir()/synthetic_studio/<hash>) unless it is already there."""
    import torch
    from tqdm import tqdm

    from framework.data.appearance import Appearance
    from framework.data.motions import Rig, axis_angle_to_matrix, build_sequence
    from framework.data.zju.layout import zju_camera_names
    from framework.data.zju.writer import ZjuWriter
    from framework.paths import data_dir

    root = Path(out) if out is not None else data_dir() / "synthetic_studio" / settings.key()
    meta_path = root / "studio.json"
    if not force and (root / "annots.npy").is_file() and meta_path.is_file():
        meta = json.loads(meta_path.read_text())
        if meta.get("key") == settings.key():
            return root
        if out is not None:
            raise FileExistsError(
                f"studio: {root} holds a sequence with other settings ({meta.get('settings')}); pick another --out "
                f"or pass --force to overwrite it."
            )
    if root.exists() and force:
        shutil.rmtree(root)
    started = root / ".studio_settings.json"  # written before the first frame: an interrupted run can be resumed
    if started.is_file() and json.loads(started.read_text()).get("key") != settings.key():
        raise FileExistsError(
            f"studio: {root} holds an unfinished sequence with other settings ({started.read_text().strip()}); pick "
            f"another --out or pass --force to start it over."
        )
    t0 = time.perf_counter()
    body = build_body(settings.body, settings.skeleton)
    rig = Rig.from_body(body)
    seq = build_sequence(rig, settings.frames, seed=settings.seed)
    F = settings.frames
    with torch.no_grad():
        local = body.posed_vertices(torch.as_tensor(seq.poses)).double().numpy()  # [F, V, 3]
    Rroot = axis_angle_to_matrix(seq.Rh.astype(np.float64))  # [F, 3, 3]
    rotated = np.einsum("fij,fvj->fvi", Rroot, local)
    Th = np.zeros((F, 3))
    Th[:, 2] = -rotated[:, :, 2].min(1)  # stand on the floor
    posed = (rotated + Th[:, None]).astype(np.float32)  # [F, V, 3]
    faces = body.faces.cpu().numpy().astype(np.int64)
    app = Appearance(body.rest_vertices.cpu().numpy(), faces, body.skin_weights.cpu().numpy(), rig, seed=settings.seed)
    wrinkles = np.stack([app.wrinkle_multiplier(p) for p in seq.poses])  # [F, V]
    rest_h = float(body.rest_vertices[:, 2].max() - body.rest_vertices[:, 2].min())
    target = np.array([0.0, 0.0, 0.55 * rest_h])
    cams = camera_ring(settings, target)
    names = zju_camera_names(settings.views)
    params = [
        {"poses": seq.poses[f].reshape(1, -1), "Rh": seq.Rh[f].reshape(1, 3), "Th": Th[f].reshape(1, 3),
         "shapes": np.zeros((1, 10), np.float32), "body": settings.body, "skeleton": settings.skeleton}
        for f in range(F)
    ]  # fmt: skip
    root.mkdir(parents=True, exist_ok=True)
    atomic_write_text(started, json.dumps({"key": settings.key(), "settings": asdict(settings)}))
    writer = ZjuWriter(root, names, image_ext=settings.image_ext, jpeg_quality=settings.jpeg_quality)
    K = np.stack([c.K for c in cams])
    R = np.stack([c.world_to_cam[:3, :3] for c in cams])
    T = np.stack([c.world_to_cam[:3, 3] for c in cams])
    writer.write_cameras(K, None, R, T)
    state = {"posed": posed, "faces": faces, "appearance": app, "wrinkles": wrinkles, "cameras": cams,
             "camera_names": names, "params": params, "root": str(root), "supersample": settings.supersample,
             "image_ext": settings.image_ext, "jpeg_quality": settings.jpeg_quality}  # fmt: skip
    todo = [f for f in range(F) if not writer.frame_done(f)]  # frames an interrupted run finished are kept
    bar = tqdm(total=F, initial=F - len(todo), desc=f"studio {settings.resolution}px x {settings.views} views",
               unit="frame", disable=not progress)  # fmt: skip
    if workers > 1 and len(todo) > 1:
        ctx = mp.get_context("fork")
        with ctx.Pool(min(workers, len(todo)), initializer=_init_worker, initargs=(state,)) as pool:
            for _ in pool.imap_unordered(_render_frame, todo):
                bar.update(1)
    else:
        _init_worker(state)
        for f in todo:
            _render_frame(f)
            bar.update(1)
    bar.close()
    meta = {
        "key": settings.key(),
        "version": STUDIO_VERSION,
        "settings": asdict(settings),
        "body": settings.body,
        "skeleton": settings.skeleton,
        "joint_names": list(rig.joint_names),
        "segments": seq.segments,
        "train_frames": seq.frames("train"),
        "novel_pose_frames": seq.frames("novel_pose"),
        "light": {"direction": list(LIGHT.direction), "ambient": LIGHT.ambient, "diffuse": LIGHT.diffuse},
        "render_seconds": round(time.perf_counter() - t0, 2),
    }
    atomic_write_text(meta_path, json.dumps(meta, indent=1))
    writer.finish(F)  # annots.npy last: its presence marks a complete sequence
    started.unlink(missing_ok=True)
    return root


def disk_size(path: Path) -> int:
    return sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file())


def main(argv: list[str] | None = None) -> None:
    d = StudioSettings()
    ap = argparse.ArgumentParser(prog="python -m framework.data.studio", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument(
        "--out", default=None, help="output directory (default: the cache, <data_dir>/synthetic_studio/<hash>)"
    )
    ap.add_argument("--resolution", type=int, default=d.resolution, help="square image size in pixels (default 512)")
    ap.add_argument("--views", type=int, default=d.views, help="cameras on the ring (default 21, like ZJU-MoCap)")
    ap.add_argument("--frames", type=int, default=d.frames, help="frames in the sequence (default 100)")
    ap.add_argument("--seed", type=int, default=d.seed, help="motion amplitudes, colours and camera azimuths")
    ap.add_argument("--body", default=d.body, help="body model registry name: anny (default) or procedural")
    ap.add_argument(
        "--skeleton", default=d.skeleton, choices=("reduced", "full"), help="anny skeleton (default reduced)"
    )
    ap.add_argument("--supersample", type=int, default=d.supersample, help="s x s rays per pixel (anti-aliasing)")
    ap.add_argument("--radius", type=float, default=d.radius, help="camera ring radius in metres (default 3)")
    ap.add_argument("--image-ext", default=d.image_ext, choices=(".jpg", ".png"), help="image format (default .jpg)")
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="render processes (default 2)")
    ap.add_argument("--force", action="store_true", help="re-render even if the sequence exists")
    a = ap.parse_args(argv)
    s = StudioSettings(
        resolution=a.resolution,
        views=a.views,
        frames=a.frames,
        seed=a.seed,
        body=a.body,
        skeleton=a.skeleton,
        supersample=a.supersample,
        radius=a.radius,
        image_ext=a.image_ext,
    )
    t = time.perf_counter()
    root = generate(s, a.out, workers=a.workers, force=a.force)
    dt = time.perf_counter() - t
    meta = json.loads((root / "studio.json").read_text())
    print(f"sequence: {root}")
    print(
        f"frames {s.frames} x views {s.views} at {s.resolution}px; this call {dt:.1f} s "
        f"(rendered in {meta['render_seconds']} s when generated); disk {disk_size(root) / 2**20:.1f} MiB"
    )
    segs = ", ".join(f"{g['name']} {g['start']}-{g['end'] - 1} [{g['split']}]" for g in meta["segments"])
    print(f"train frames {len(meta['train_frames'])}, novel-pose frames {len(meta['novel_pose_frames'])} ({segs})")


if __name__ == "__main__":
    main()

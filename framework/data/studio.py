"""The synthetic studio: a multi-view video of a posed, clothed body, ray-cast and written in the ZJU-MoCap layout.

    python -m framework.data.studio data=synthetic_studio profile=gpu data.root=DIR data.seed=0

What it makes (deterministic for the settings; cached by a hash of them, so a second run reuses the sequence, and an
interrupted one resumes: the frames it finished are kept):
- Cameras: a ring of `num_views` calibrated pinhole cameras at `radius` m around the subject, heights alternating around
  1.3 m, all looking at the body's centre (OpenCV K/R/T, D = 0), like ZJU-MoCap's capture dome.
- Motion (`framework.data.motions`): the anny walk cycle, arm raises, squats and kicks for training, and a held-out
  turn-and-reach motion for novel-pose evaluation; each frame's pose is stored with the body-model name.
  `motion=idle` is a near-static capture (a slight nod and arm sway), `motion=arms` moves only the arms.
- Look (`LOOKS`): `default` is matte cloth; `glossy` adds a view-dependent highlight and deeper pose-dependent folds.
- Appearance (`framework.data.appearance`): striped, printed and seamed clothing as a solid texture on the rest-pose
  surface, wrinkle shading that follows joint flexion, and self-shadows from a fixed light (Embree shadow rays).
- Ground truth by ray casting the linear-blend-skinned mesh (`framework.data.raycast`): images, masks, posed
  vertices; `studio.json` next to `annots.npy` records the settings, the motion segments and which frames are the
  novel-pose (held-out) frames.

The subject stands on the floor z = 0 (each frame's Th lifts the lowest posed vertex to 0) and turns with Rh.

Capture imperfections (all off by default; conf/data/synthetic_studio_realistic.yaml turns them on for Table 4):
- `pose_noise_deg`, `root_noise_m`: the stored params (and the fitted mesh in vertices/) carry EasyMocap-like
  fitting noise (`framework.data.imperfections`); the images are rendered from the clean pose.
- `mask_error_px`: mask_cihp/ holds parser-like masks with boundary errors of up to that many pixels (the loader
  reads mask_cihp/ first, as Animatable NeRF does); mask/ keeps the exact masks, the images stay exact.
- `garment`: "skirt" adds a loose skirt driven by the pelvis with lag and swing (`framework.data.garment`), rendered
  and in the masks but not in the body fit (vertices/), as real clothing is.
- `subject_height_fraction`: framing like ZJU-MoCap's; the camera ring's radius is chosen so the rest-pose body is
  this fraction of the image height (`radius` is then ignored).
With pose noise or a garment, ground_truth/ holds what the annotations do not: the clean params and body vertices
(params/, vertices/) and the skirt's vertices (garment/, plus garment_rest.npy and garment_faces.npy).
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing as mp
import os
import shutil
import sys
import time
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np

from framework.atomic import atomic_write_text
from framework.data import raycast
from framework.data.garment import skirt_albedo

STUDIO_VERSION = 2
LIGHT = raycast.Shading(direction=(0.45, -0.55, 0.7), ambient=0.32, diffuse=0.78, shadows=True)
GARMENTS = ("none", "skirt")
IMPERFECTION_DEFAULTS = {
    "pose_noise_deg": 0.0,
    "root_noise_m": 0.0,
    "mask_error_px": 0.0,
    "garment": "none",
    "garment_lag": 0.5,
    "subject_height_fraction": None,
}
#: looks (`StudioSettings.look`): shading plus the strength of the pose-dependent wrinkle shading (fine bands, broad
#: fold shade). `default` is matte (Lambertian) cloth; `glossy` adds a broad white highlight that moves with the
#: viewer (view-dependent colour) and deeper folds (stronger pose-dependent shading).
LOOKS: dict[str, tuple[raycast.Shading, float, float]] = {
    "default": (LIGHT, 0.55, 0.35),
    "glossy": (replace(LIGHT, specular=0.45, shininess=12.0), 0.8, 0.55),
}


#: the hash input's names of the fields renamed by the dataset-key rule (framework.dataset_keys), so a studio
#: rendered before the rename keeps its key and its cache
HASH_NAMES = {"num_views": "views", "num_frames": "frames"}


@dataclass(frozen=True)
class StudioSettings:
    """What the rendered sequence depends on (its cache key); the synthetic_studio dataset's config keys of the same
    names. Numbers are normalised to their field's type, so `3` and `3.0` name the same sequence."""

    resolution: int = 512
    num_views: int = 21
    num_frames: int = 100
    seed: int = 0
    body: str = "anny"
    skeleton: str = "reduced"  # anny only: "reduced" (22 bones) or "full" (104)
    supersample: int = 1
    radius: float = 3.0
    fov_deg: float = 45.0
    image_ext: str = ".jpg"
    jpeg_quality: int = 95
    # capture imperfections (module docstring); at these defaults the output is what it was before they existed
    pose_noise_deg: float = 0.0
    root_noise_m: float = 0.0
    mask_error_px: float = 0.0
    garment: str = "none"  # "none" | "skirt"
    garment_lag: float = 0.5
    subject_height_fraction: float | None = None
    motion: str = "default"  # a program of framework.data.motions.PROGRAMS: default | idle | arms
    look: str = "default"  # a key of LOOKS: default (matte) | glossy

    def __post_init__(self) -> None:
        from framework.data.motions import PROGRAMS

        self._normalise_numbers()
        if self.num_views < 1 or self.num_frames < 1:
            raise ValueError(f"studio: num_views and num_frames must be >= 1, got {self.num_views}, {self.num_frames}.")
        if self.garment not in GARMENTS:
            raise ValueError(f"studio: garment must be one of {GARMENTS}, got '{self.garment}'.")
        if self.subject_height_fraction is not None and not 0.05 < self.subject_height_fraction <= 1.5:
            raise ValueError(
                f"studio: subject_height_fraction must be in (0.05, 1.5] (the body's share of the image height), got "
                f"{self.subject_height_fraction}."
            )
        for name in ("pose_noise_deg", "root_noise_m", "mask_error_px"):
            if getattr(self, name) < 0:
                raise ValueError(f"studio: {name} must be >= 0, got {getattr(self, name)}.")
        if self.motion not in PROGRAMS:
            raise ValueError(f"studio: motion '{self.motion}' is not one of {sorted(PROGRAMS)}.")
        if self.look not in LOOKS:
            raise ValueError(f"studio: look '{self.look}' is not one of {sorted(LOOKS)}.")

    def _normalise_numbers(self) -> None:
        """int / float fields as int / float (a config may give 3 for 3.0): the key hashes their JSON text."""
        casts = {"int": (int, "an integer"), "float": (float, "a number"), "float | None": (float, "a number or null")}
        for f in fields(self):
            cast, expected = casts.get(str(f.type), (None, ""))
            value = getattr(self, f.name)
            if cast is None or value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, int | float) or (cast is int and value != int(value)):
                raise ValueError(f"studio: {f.name} must be {expected}, got {value!r}.")
            object.__setattr__(self, f.name, cast(value))

    def key(self) -> str:
        """Hash of the settings; knobs left at their defaults are left out, so sequences rendered before a knob
        existed keep their key (and their cache), and renamed fields are hashed under their old names."""
        values = {HASH_NAMES.get(k, k): v for k, v in asdict(self).items()}
        for name, default in {**IMPERFECTION_DEFAULTS, "motion": "default", "look": "default"}.items():
            if values[name] == default:
                del values[name]
        blob = json.dumps({"version": STUDIO_VERSION, **values}, sort_keys=True)
        return hashlib.sha1(blob.encode()).hexdigest()[:12]

    @property
    def has_ground_truth(self) -> bool:
        """Whether the stored annotations differ from what was rendered (then ground_truth/ is written)."""
        return self.pose_noise_deg > 0 or self.root_noise_m > 0 or self.garment != "none"


def build_body(name: str, skeleton: str = "reduced"):
    """The body model through the registry (anny takes a skeleton option)."""
    from framework import plugins
    from framework.registry import BODIES

    plugins.load_plugins()
    kwargs = {"skeleton": skeleton} if name == "anny" else {}
    return BODIES.build(name, **kwargs)


def ring_radius(settings: StudioSettings, subject_height: float) -> float:
    """The ring radius: `radius`, or the distance at which a subject of this height fills `subject_height_fraction`
    of the image height (pinhole: fraction = height / (2 r tan(fov / 2)))."""
    if settings.subject_height_fraction is None:
        return settings.radius
    return subject_height / (2.0 * settings.subject_height_fraction * np.tan(np.deg2rad(settings.fov_deg) / 2))


def camera_ring(settings: StudioSettings, target: np.ndarray, radius: float | None = None) -> list[raycast.Camera]:
    """`num_views` cameras evenly spaced on a ring (seeded azimuth offset), heights alternating 1.1 / 1.5 m."""
    rng = np.random.default_rng(settings.seed + 7)
    az0 = rng.uniform(0, 2 * np.pi)
    K = raycast.intrinsics(settings.fov_deg, settings.resolution, settings.resolution)
    radius = settings.radius if radius is None else radius
    cams = []
    for i in range(settings.num_views):
        az = az0 + 2 * np.pi * i / settings.num_views
        h = 1.1 + 0.4 * (i % 2)
        eye = np.array([radius * np.cos(az), radius * np.sin(az), h])
        cams.append(raycast.Camera(K, raycast.look_at(eye, target), settings.resolution, settings.resolution))
    return cams


# ------------------------------------------------------------------------------------------------ workers
_STATE: dict = {}


def _init_worker(state: dict) -> None:
    _STATE.clear()
    _STATE.update(state)


def _render_frame(f: int) -> int:
    from framework.data.imperfections import parser_like_mask
    from framework.data.zju.writer import ZjuWriter

    s = _STATE
    verts = s["posed"][f].astype(np.float64)  # [V, 3] world, the clean pose
    faces = s["faces"]
    app = s["appearance"]
    wrinkle = s["wrinkles"][f]  # [V]
    rest = app.rest
    skirt = s["skirt"]
    num_body_faces = len(faces)
    if skirt is not None:  # one mesh: body faces first, then the skirt's
        verts = np.concatenate([verts, s["skirt_posed"][f]])
        faces = np.concatenate([faces, skirt.faces + len(rest)])

    def color(face_ids: np.ndarray, bary: np.ndarray, _points: np.ndarray) -> np.ndarray:
        out = np.empty((len(face_ids), 3), np.float32)
        body = face_ids < num_body_faces
        tri = faces[face_ids[body]]  # [N, 3]
        rest_pts = np.einsum("nk,nkc->nc", bary[body], rest[tri])
        m = np.einsum("nk,nk->n", bary[body], wrinkle[tri])
        out[body] = app.albedo(face_ids[body], rest_pts) * m[:, None]
        if skirt is not None and not body.all():
            tri = skirt.faces[face_ids[~body] - num_body_faces]
            out[~body] = skirt_albedo(np.einsum("nk,nkc->nc", bary[~body], skirt.rest[tri]))
        return out

    caster = raycast.RayCaster(verts, faces)
    normals = raycast.vertex_normals(verts, faces)
    imgs, masks, parsed = [], [], []
    for v, cam in enumerate(s["cameras"]):
        r = raycast.render(
            verts,
            faces,
            cam,
            color_fn=color,
            shading=s["shading"],
            normals=normals,
            supersample=s["supersample"],
            caster=caster,
        )
        imgs.append(r.rgb)
        masks.append(r.mask)
        if s["mask_error_px"] > 0:
            rng = np.random.default_rng([s["seed"], f, v, 31])
            parsed.append(parser_like_mask(r.mask, s["mask_error_px"], rng))
    writer = ZjuWriter(s["root"], s["camera_names"], image_ext=s["image_ext"], jpeg_quality=s["jpeg_quality"])
    if parsed:  # before write_frame, which marks the frame done
        writer.write_masks(f, np.stack(parsed), "mask_cihp")
    writer.write_frame(f, np.stack(imgs), np.stack(masks), params=s["params"][f], vertices=s["fitted"][f])
    return f


def generate(
    settings: StudioSettings,
    out: str | Path | None = None,
    workers: int = 2,
    progress: bool = True,
    force: bool = False,
) -> Path:
    """Render the sequence into `out` (default: data_dir()/synthetic_studio/<hash>) unless it is already there."""
    import torch
    from tqdm import tqdm

    from framework.data.appearance import Appearance
    from framework.data.motions import PROGRAMS, Rig, axis_angle_to_matrix, build_sequence
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
    seq = build_sequence(rig, settings.num_frames, seed=settings.seed, program=PROGRAMS[settings.motion])
    shading, wrinkle_strength, broad_strength = LOOKS[settings.look]
    F = settings.num_frames
    with torch.no_grad():
        local = body.posed_vertices(torch.as_tensor(seq.poses)).double().numpy()  # [F, V, 3]
    Rroot = axis_angle_to_matrix(seq.Rh.astype(np.float64))  # [F, 3, 3]
    rotated = np.einsum("fij,fvj->fvi", Rroot, local)
    Th = np.zeros((F, 3))
    Th[:, 2] = -rotated[:, :, 2].min(1)  # stand on the floor
    posed = (rotated + Th[:, None]).astype(np.float32)  # [F, V, 3]
    faces = body.faces.cpu().numpy().astype(np.int64)
    app = Appearance(
        body.rest_vertices.cpu().numpy(),
        faces,
        body.skin_weights.cpu().numpy(),
        rig,
        seed=settings.seed,
        wrinkle_strength=wrinkle_strength,
        broad_strength=broad_strength,
    )
    wrinkles = np.stack([app.wrinkle_multiplier(p) for p in seq.poses])  # [F, V]
    rest_h = float(body.rest_vertices[:, 2].max() - body.rest_vertices[:, 2].min())
    framed = settings.subject_height_fraction is not None
    target = np.array([0.0, 0.0, (0.5 if framed else 0.55) * rest_h])
    radius = ring_radius(settings, rest_h)
    cams = camera_ring(settings, target, radius)
    names = zju_camera_names(settings.num_views)
    skirt, skirt_posed = _skirt(settings, body, rig, seq.poses, Rroot, Th)
    fit_poses, fit_Th, fitted = _fitted(settings, body, seq.poses, Rroot, Th, posed)
    params = [
        {
            "poses": fit_poses[f].reshape(1, -1),
            "Rh": seq.Rh[f].reshape(1, 3),
            "Th": fit_Th[f].reshape(1, 3),
            "shapes": np.zeros((1, 10), np.float32),
            "body": settings.body,
            "skeleton": settings.skeleton,
        }
        for f in range(F)
    ]
    root.mkdir(parents=True, exist_ok=True)
    atomic_write_text(started, json.dumps({"key": settings.key(), "settings": asdict(settings)}))
    writer = ZjuWriter(root, names, image_ext=settings.image_ext, jpeg_quality=settings.jpeg_quality)
    K = np.stack([c.K for c in cams])
    R = np.stack([c.world_to_cam[:3, :3] for c in cams])
    T = np.stack([c.world_to_cam[:3, 3] for c in cams])
    writer.write_cameras(K, None, R, T)
    state = {
        "posed": posed,
        "faces": faces,
        "appearance": app,
        "wrinkles": wrinkles,
        "cameras": cams,
        "camera_names": names,
        "params": params,
        "root": str(root),
        "supersample": settings.supersample,
        "image_ext": settings.image_ext,
        "jpeg_quality": settings.jpeg_quality,
        "fitted": fitted,
        "skirt": skirt,
        "skirt_posed": skirt_posed,
        "mask_error_px": settings.mask_error_px,
        "seed": settings.seed,
        "shading": shading,
    }
    todo = [f for f in range(F) if not writer.frame_done(f)]  # frames an interrupted run finished are kept
    bar = tqdm(
        total=F,
        initial=F - len(todo),
        desc=f"studio {settings.resolution}px x {settings.num_views} views",
        unit="frame",
        disable=not progress,
    )
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
    if settings.has_ground_truth:
        clean = [{**p, "poses": seq.poses[f].reshape(1, -1), "Th": Th[f].reshape(1, 3)} for f, p in enumerate(params)]
        _write_ground_truth(root, writer, clean, posed, skirt, skirt_posed)
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
        "camera_ring_radius": radius,
        "imperfections": {name: getattr(settings, name) for name in IMPERFECTION_DEFAULTS},
        "ground_truth": "ground_truth" if settings.has_ground_truth else None,
        "light": {
            "direction": list(shading.direction),
            "ambient": shading.ambient,
            "diffuse": shading.diffuse,
            "specular": shading.specular,
            "shininess": shading.shininess,
        },
        "render_seconds": round(time.perf_counter() - t0, 2),
    }
    atomic_write_text(meta_path, json.dumps(meta, indent=1))
    writer.finish(F)  # annots.npy last: its presence marks a complete sequence
    started.unlink(missing_ok=True)
    return root


def _skirt(settings: StudioSettings, body, rig, poses: np.ndarray, Rroot: np.ndarray, Th: np.ndarray):
    """(Skirt, its world vertices [F, Vs, 3] float32) for garment="skirt", else (None, None)."""
    import torch

    from framework.data.garment import build_skirt, skirt_motion

    if settings.garment == "none":
        return None, None
    pelvis = rig.index["pelvis"]
    skirt = build_skirt(
        body.rest_vertices.cpu().numpy(),
        body.skin_weights.cpu().numpy(),
        list(body.joint_names),
        rig.rest_joints[pelvis],
    )
    with torch.no_grad():
        G = body.bone_transforms(torch.as_tensor(poses)).double().numpy()  # [F, J, 4, 4] rest -> posed (body frame)
    root = np.tile(np.eye(4), (len(poses), 1, 1))
    root[:, :3, :3], root[:, :3, 3] = Rroot, Th
    return skirt, skirt_motion(skirt, root @ G[:, pelvis], lag=settings.garment_lag).astype(np.float32)


def _fitted(settings: StudioSettings, body, poses: np.ndarray, Rroot: np.ndarray, Th: np.ndarray, posed: np.ndarray):
    """The annotation a fit would give: (poses [F, J, 3], Th [F, 3], body vertices [F, V, 3]), noisy when asked."""
    import torch

    from framework.data.imperfections import perturb_poses

    if settings.pose_noise_deg == 0 and settings.root_noise_m == 0:
        return poses, Th, posed
    rng = np.random.default_rng([settings.seed, 101])
    fit_poses, fit_Th = perturb_poses(poses, Th, settings.pose_noise_deg, settings.root_noise_m, rng)
    with torch.no_grad():
        local = body.posed_vertices(torch.as_tensor(fit_poses)).double().numpy()  # [F, V, 3]
    fitted = np.einsum("fij,fvj->fvi", Rroot, local) + fit_Th[:, None].astype(np.float64)
    return fit_poses, fit_Th, fitted.astype(np.float32)


def _write_ground_truth(root: Path, writer, params: list[dict], posed: np.ndarray, skirt, skirt_posed) -> None:
    """ground_truth/: the clean params and body vertices, and the skirt (rest mesh and per-frame vertices)."""
    from framework.data.zju.layout import normalize_params, save_pickled_dict

    gt = root / "ground_truth"
    for sub in ("params", "vertices") + (("garment",) if skirt is not None else ()):
        (gt / sub).mkdir(parents=True, exist_ok=True)
    for f, p in enumerate(params):
        n = writer.file_number(f)
        save_pickled_dict(gt / "params" / f"{n}.npy", normalize_params(p, f"frame {f}"))
        np.save(gt / "vertices" / f"{n}.npy", posed[f])
        if skirt is not None:
            np.save(gt / "garment" / f"{n}.npy", skirt_posed[f])
    if skirt is not None:
        np.save(gt / "garment_rest.npy", skirt.rest.astype(np.float32))
        np.save(gt / "garment_faces.npy", skirt.faces.astype(np.int32))


def disk_size(path: Path) -> int:
    return sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file())


def generate_from_config(data: dict, force: bool = False) -> tuple[Path, StudioSettings]:
    """Render (or find) the studio a `data=synthetic_studio*` config describes: its folder and settings. The config's
    other keys say how the sequence is read, not what is rendered; composing it already rejected unknown ones."""
    names = {f.name for f in fields(StudioSettings)}
    settings = StudioSettings(**{k: v for k, v in data.items() if k in names})
    workers = int(data.get("workers") or min(2, os.cpu_count() or 1))
    return generate(settings, data.get("root"), workers=workers, force=force), settings


def main() -> int:
    from omegaconf import DictConfig, OmegaConf

    from framework.cli import hydra_main
    from framework.errors import SplatrigError, reported_as_message

    @hydra_main("studio")
    def _main(cfg: DictConfig) -> None:
        with reported_as_message():
            data = OmegaConf.to_container(cfg.data, resolve=True)
            if not str(data.get("name", "")).startswith("synthetic_studio"):
                raise SplatrigError(
                    f"data={data.get('name')}: the studio renders synthetic_studio* datasets (data=synthetic_studio)"
                )
            t = time.perf_counter()
            root, s = generate_from_config(data, force=bool(cfg.force))
            dt = time.perf_counter() - t
        meta = json.loads((root / "studio.json").read_text())
        print(f"sequence: {root}")
        print(
            f"frames {s.num_frames} x views {s.num_views} at {s.resolution}px; this call {dt:.1f} s "
            f"(rendered in {meta['render_seconds']} s when generated); disk {disk_size(root) / 2**20:.1f} MiB"
        )
        segs = ", ".join(f"{g['name']} {g['start']}-{g['end'] - 1} [{g['split']}]" for g in meta["segments"])
        print(f"train frames {len(meta['train_frames'])}, novel-pose frames {len(meta['novel_pose_frames'])} ({segs})")

    _main()
    return 0


if __name__ == "__main__":
    sys.exit(main())

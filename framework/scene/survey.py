"""The scene survey: what a multi-view capture of a body needs, measured from the dataset alone.

Measured on the training split (views, frames and images a model would be fitted to):
- joints: each joint's rotation range over the training frames (the largest geodesic angle between two frames'
  local rotations); a joint moves when that exceeds `moving_deg`.
- silhouettes: mean foreground area per view (pixels at the training resolution) and as a fraction of the image.
- appearance, through the body-surface correspondence: each sampled frame's stored posed vertices (`vertices(frame)`)
  with the body's faces are ray-cast from every training camera (`framework.data.raycast`, exact visibility), so
  every interior pixel knows which triangle of the body it shows. Images are low-passed first (`blur_px`, so texture
  finer than a pixel does not alias differently in different views); pixels near a silhouette edge or seeing a
  triangle at a grazing angle are left out. Per triangle:
  * view dependence: the spread (unbiased standard deviation, RMS over triangles and channels, colour units 0..1) of
    the triangle's colour across the views of one frame. Matte cloth under fixed light has none.
  * pose dependence: the spread of the triangle's view-averaged colour across the sampled frames, minus (in
    variance) the spread between each frame and the training frame closest to it in pose (root rotation included):
    that pair differs by noise and sampling, not by pose, so it is the floor the pose effect is measured above.
- skin offset: the mean distance in pixels between the posed body mesh's silhouette and the captured mask (pixels that
  differ / silhouette boundary length); near 0 when the surface follows the body model's skinning (tight clothing).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from framework.atomic import atomic_write_text
from framework.errors import SplatrigError

SURVEY_VERSION = 2
MIN_COS = 0.3  # triangles seen at a more grazing angle than ~73 degrees are left out of the colour statistics
INTERIOR_PX = 1  # pixels closer than this (or than the low-pass reach) to a silhouette edge are left out
DEPTH_EDGE_M = 0.05  # ... and so are pixels near a depth step larger than this (an occlusion edge inside the body)


class SurveyError(SplatrigError):
    """The dataset cannot be surveyed (no body poses or posed vertices, or a body that does not fit them)."""


@dataclass
class SceneSurvey:
    """Measurements of one training split; `joints` maps joint name -> rotation range in degrees."""

    key: str
    dataset: str
    body: str
    width: int
    height: int
    views: int
    frames: int
    joints: dict[str, float]
    moving_deg: float
    silhouette_px: float
    silhouette_fraction: float
    silhouette_px_per_view: dict[int, float]
    view_dependence: float
    pose_dependence: float
    pose_noise: float
    skin_offset_px: float
    sampled_frames: list[int] = field(default_factory=list)
    seconds: float = 0.0
    version: int = SURVEY_VERSION

    @property
    def moving_joints(self) -> list[str]:
        return [name for name, deg in self.joints.items() if deg > self.moving_deg]

    @property
    def still_joints(self) -> list[str]:
        return [name for name, deg in self.joints.items() if deg <= self.moving_deg]

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SceneSurvey:
        data = dict(data)
        data["silhouette_px_per_view"] = {int(k): float(v) for k, v in data["silhouette_px_per_view"].items()}
        return cls(**data)

    def report(self) -> str:
        """A short readable summary (what a person reads before training)."""
        moving = ", ".join(f"{n} {self.joints[n]:.0f}°" for n in self.moving_joints) or "none"
        still = ", ".join(self.still_joints) or "none"
        lines = [
            f"scene survey of {self.dataset}",
            f"  data: {self.views} training views x {self.frames} frames at {self.width}x{self.height}, body "
            f"'{self.body}'",
            f"  joints moving (> {self.moving_deg:g}° over the training frames): {moving}",
            f"  joints still: {still}",
            f"  silhouette: {self.silhouette_px:.0f} px per view ({100 * self.silhouette_fraction:.1f}% of the image)",
            f"  view-dependent colour: {self.view_dependence:.4f} (std of a surface point across views, 0..1)",
            f"  pose-dependent colour: {self.pose_dependence:.4f} (across frames, above the similar-pose floor "
            f"{self.pose_noise:.4f})",
            f"  skin offset: {self.skin_offset_px:.2f} px (posed body silhouette vs masks)",
            f"  measured on frames {self.sampled_frames} in {self.seconds:.1f} s",
        ]
        return "\n".join(lines)


# ------------------------------------------------------------------------------------------------- joints
def joint_rotation_ranges(poses: torch.Tensor) -> torch.Tensor:
    """poses [F, J, 3] axis-angle -> [J] the largest geodesic angle (radians) between any two frames' rotations."""
    from framework.geometry import axis_angle_to_rotmat

    R = axis_angle_to_rotmat(poses.double())  # [F, J, 3, 3]
    out = torch.zeros(poses.shape[1], dtype=torch.float64)
    for j in range(poses.shape[1]):
        trace = torch.einsum("fab,gab->fg", R[:, j], R[:, j])  # tr(R_f^T R_g)
        out[j] = torch.arccos(((trace - 1) / 2).clamp(-1.0, 1.0)).max()
    return out


def _geodesic(Ra: torch.Tensor, Rb: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] x [..., 3, 3] -> [...] angle between rotations."""
    trace = (Ra * Rb).sum((-1, -2))
    return torch.arccos(((trace - 1) / 2).clamp(-1.0, 1.0))


def nearest_pose_frames(poses: torch.Tensor, roots: torch.Tensor | None, frames: list[int], candidates: list[int]):
    """For each frame in `frames`, the other candidate frame with the closest pose: mean joint geodesic angle plus the
    root rotation's angle (the light is fixed in the world, so the heading matters to shading)."""
    from framework.geometry import axis_angle_to_rotmat

    R = axis_angle_to_rotmat(poses.double())  # [F, J, 3, 3]
    out = []
    cand = torch.as_tensor(candidates)
    for f in frames:
        d = _geodesic(R[f].unsqueeze(0), R[cand]).mean(-1)  # [Fc]
        if roots is not None:
            d = d + _geodesic(roots[f, :3, :3].double().unsqueeze(0), roots[cand, :3, :3].double())
        d[cand == f] = math.inf
        out.append(int(cand[int(torch.argmin(d))]))
    return out


# ------------------------------------------------------------------------------------------------- appearance
def _means_by(keys: np.ndarray, groups: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean of `values` [P, 3] per (key, group) pair -> (keys [U], groups [U], means [U, 3])."""
    num_groups = int(groups.max()) + 1 if groups.size else 1
    combo, inverse = np.unique(keys * num_groups + groups, return_inverse=True)
    counts = np.bincount(inverse)
    sums = np.stack([np.bincount(inverse, weights=values[:, c]) for c in range(3)], axis=1)
    return combo // num_groups, combo % num_groups, sums / counts[:, None]


def _spread(keys: np.ndarray, groups: np.ndarray, values: np.ndarray) -> tuple[float, int]:
    """How much a surface patch's colour differs between groups (views, or frames): the unbiased variance across
    groups of each patch's per-group mean, summed over patches seen in >= 2 groups and channels, and the number of
    (patch, channel) terms in that sum."""
    if keys.size == 0:
        return 0.0, 0
    k, _, means = _means_by(keys, groups, values)
    patches, inverse = np.unique(k, return_inverse=True)
    n = np.bincount(inverse)
    centre = np.stack([np.bincount(inverse, weights=means[:, c]) for c in range(3)], axis=1) / n[:, None]
    sq = np.stack([np.bincount(inverse, weights=(means[:, c] - centre[inverse, c]) ** 2) for c in range(3)], axis=1)
    ok = n >= 2
    return float((sq[ok] / (n[ok, None] - 1)).sum()), int(3 * ok.sum())


@dataclass
class _Samples:
    """Valid pixels of one frame: the surface patch each shows, the view, the low-passed colour."""

    keys: np.ndarray  # [P] int64 patch ids (a voxel of the rest-pose surface)
    views: np.ndarray  # [P]
    colours: np.ndarray  # [P, 3]

    def view_averaged(self) -> tuple[np.ndarray, np.ndarray]:
        """(patch ids [U], colour [U, 3]): each patch's mean over the views that see it, every view counted once."""
        k, _, means = _means_by(self.keys, self.views, self.colours)
        patches, inverse = np.unique(k, return_inverse=True)
        n = np.bincount(inverse)
        return patches, np.stack([np.bincount(inverse, weights=means[:, c]) for c in range(3)], axis=1) / n[:, None]


class _Sampler:
    """Ray-casts the stored posed mesh from each training camera; every valid pixel gets the rest-pose surface patch it
    shows (patches one pixel footprint wide, so two views compare the same few square centimetres of cloth)."""

    def __init__(self, dataset, body, blur_px: float) -> None:
        self.dataset = dataset
        self.faces = body.faces.cpu().numpy().astype(np.int64)
        self.rest = body.rest_vertices.detach().cpu().double().numpy()  # [V, 3]
        self.blur_px = blur_px
        self.views = list(dataset.views)
        self.index = {dataset.sample(i): i for i in range(len(dataset))}  # (frame, view) -> item
        self.silhouette: dict[int, list[float]] = {v: [] for v in self.views}
        self.offset_px = 0.0
        self.boundary_px = 0.0
        self.patch_m: float | None = None

    def _patch_keys(self, fid: np.ndarray, bary: np.ndarray) -> np.ndarray:
        points = np.einsum("nk,nkc->nc", bary.astype(np.float64), self.rest[self.faces[fid]])  # [P, 3] rest pose
        cell = np.floor(points / self.patch_m).astype(np.int64) + (1 << 20)
        return (cell[:, 0] << 42) | (cell[:, 1] << 21) | cell[:, 2]

    def frame(self, f: int, with_silhouettes: bool) -> _Samples:
        import cv2

        from framework.data import raycast
        from framework.data.boundary import boundary_mask

        verts = np.asarray(self.dataset.vertices(f), dtype=np.float64)  # [V, 3] world
        caster = raycast.RayCaster(verts, self.faces)
        tri = verts[self.faces]
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-20)  # [T, 3]
        keys, views, colours = [], [], []
        for view in self.views:
            item = self.dataset[self.index[(f, view)]]
            cams = item.cameras
            cam = raycast.Camera(
                cams.K[0].double().numpy(), cams.world_to_cam[0].double().numpy(), cams.width, cams.height
            )
            origins, dirs = raycast.camera_rays(cam)
            fid, bary, depth = caster.intersect(origins, dirs)
            H, W = cams.height, cams.width
            if self.patch_m is None and (fid >= 0).any():  # one pixel's footprint on the subject
                self.patch_m = float(np.median(depth[fid >= 0])) / float(cam.K[0, 0])
            mask = item.mask[0].numpy()  # [H, W] coverage
            mesh = (fid >= 0).reshape(H, W)
            fg = mask >= 0.5
            if with_silhouettes:
                self.silhouette[view].append(float(mask.sum()))
                self.offset_px += float((mesh ^ fg).sum())
                self.boundary_px += float((fg & (boundary_mask(fg, 1) == 0)).sum())
            image = item.image[0].numpy().astype(np.float32)  # [H, W, 3]
            if self.blur_px > 0:
                image = cv2.GaussianBlur(image, (0, 0), self.blur_px)
            keep_out = max(INTERIOR_PX, int(math.ceil(2 * self.blur_px)))  # reach of the low-pass filter
            interior = (boundary_mask(mask >= 0.99, keep_out) > 0) & (mask >= 0.99)
            interior &= (boundary_mask(mesh, keep_out) > 0) & mesh
            # inner occlusion edges (an arm in front of the torso) mix two surfaces after blurring: leave them out
            z = np.where(fid >= 0, depth, 1e3).reshape(H, W).astype(np.float32)
            kernel = np.ones((2 * keep_out + 1, 2 * keep_out + 1), np.uint8)
            interior &= (cv2.dilate(z, kernel) - cv2.erode(z, kernel)) < DEPTH_EDGE_M
            d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
            cos = np.abs(np.einsum("nc,nc->n", normals[np.maximum(fid, 0)], d))
            ok = interior.ravel() & (cos > MIN_COS) & (fid >= 0)
            keys.append(self._patch_keys(fid[ok], bary[ok]))
            views.append(np.full(int(ok.sum()), view, np.int64))
            colours.append(image.reshape(-1, 3)[ok].astype(np.float64))
        return _Samples(np.concatenate(keys), np.concatenate(views), np.concatenate(colours))


# ------------------------------------------------------------------------------------------------- profile
def survey_key(dataset, max_frames: int, blur_px: float, moving_deg: float) -> str:
    """Identifies a survey: the data (root, training views and frames, resolution) and the measurement settings."""
    ident = {
        "version": SURVEY_VERSION,
        "root": str(Path(dataset.root if dataset.root is not None else "").resolve()),
        "views": [int(v) for v in dataset.views],
        "frames": [int(f) for f in dataset.frame_ids],
        "size": [int(dataset.cameras.width), int(dataset.cameras.height)],
        "settings": [int(max_frames), float(blur_px), float(moving_deg)],
    }
    return hashlib.sha1(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:12]


def survey_path(dataset, key: str) -> Path:
    """`<dataset root>/scene_survey-<key>.yaml` beside the data, or under the project cache if that is read-only."""
    root = dataset.root
    if root is not None and os.access(root, os.W_OK):
        return Path(root) / f"scene_survey-{key}.yaml"
    from framework.paths import cache_dir

    name = re.sub(r"[^A-Za-z0-9_.-]", "_", str(Path(root).resolve()) if root is not None else "dataset")
    return cache_dir() / "scene_surveys" / name / f"scene_survey-{key}.yaml"


def _check_surveyable(dataset, body) -> None:
    what = dataset.registry_name or type(dataset).__name__
    if dataset.poses() is None:
        raise SurveyError(
            f"data={what}: the scene survey needs a body dataset with per-frame poses and posed vertices "
            f"(e.g. data=synthetic_studio or data=zju_mocap); this dataset has none. Survey a body capture instead."
        )
    try:
        verts = dataset.vertices(dataset.frame_ids[0])
    except (OSError, ValueError, KeyError) as exc:
        raise SurveyError(
            f"data={what}: the scene survey needs the posed body vertices of every frame (a vertices/ folder in the "
            f"ZJU-MoCap layout, as EasyMocap writes it); reading frame {dataset.frame_ids[0]} failed: {exc}"
        ) from None
    joints = dataset.poses().shape[1]
    if body is None or verts.shape[0] != body.rest_vertices.shape[0] or joints != body.num_joints:
        found = None if body is None else body.rest_vertices.shape[0]
        raise SurveyError(
            f"data={what}: the stored vertices and poses have {verts.shape[0]} points and {joints} joints but body "
            f"'{None if body is None else body.registry_name}' has {found} and "
            f"{None if body is None else body.num_joints}; select "
            f"the body (and skeleton) the data was made with "
            f"(the dataset says '{dataset.body_name}'), e.g. body={dataset.body_name}."
        )


def survey_dataset(
    dataset, body, max_frames: int = 12, blur_px: float = 1.0, moving_deg: float = 5.0, progress: bool = True
) -> SceneSurvey:
    """Measure a training split (see the module docstring). `body` supplies the faces and joint names."""
    from tqdm.auto import tqdm

    _check_surveyable(dataset, body)
    t0 = time.perf_counter()
    frames = list(dataset.frame_ids)
    poses = dataset.poses()  # [F_total, J, 3]
    ranges = joint_rotation_ranges(poses[frames])
    names = list(body.joint_names)
    roots = dataset.roots()
    take = max(1, min(int(max_frames), len(frames)))
    sampled = [frames[int(i)] for i in np.linspace(0, len(frames) - 1, take).round().astype(int)]
    sampled = list(dict.fromkeys(sampled))
    partners = nearest_pose_frames(poses, roots, sampled, frames) if len(frames) > 1 else []
    sampler = _Sampler(dataset, body, blur_px)
    view_var, view_n = 0.0, 0
    pose_keys, pose_frames, pose_colours = [], [], []
    floor_var, floor_n = 0.0, 0
    bar = tqdm(total=len(sampled) + len(partners), desc="scene survey", unit="frame", disable=not progress)
    for i, f in enumerate(sampled):
        samples = sampler.frame(f, with_silhouettes=True)
        bar.update(1)
        v, n = _spread(samples.keys, samples.views, samples.colours)
        view_var, view_n = view_var + v, view_n + n
        keys, colours = samples.view_averaged()
        pose_keys.append(keys)
        pose_frames.append(np.full(len(keys), i, np.int64))
        pose_colours.append(colours)
        if partners:
            pkeys, pcolours = sampler.frame(partners[i], with_silhouettes=False).view_averaged()
            bar.update(1)
            both = np.concatenate([np.zeros(len(keys), np.int64), np.ones(len(pkeys), np.int64)])
            v, n = _spread(np.concatenate([keys, pkeys]), both, np.concatenate([colours, pcolours]))
            floor_var, floor_n = floor_var + v, floor_n + n
    bar.close()
    total_var, total_n = _spread(np.concatenate(pose_keys), np.concatenate(pose_frames), np.concatenate(pose_colours))
    total = total_var / max(total_n, 1)
    floor = floor_var / max(floor_n, 1)
    per_view = {int(v): float(np.mean(a)) for v, a in sampler.silhouette.items() if a}
    W, H = int(dataset.cameras.width), int(dataset.cameras.height)
    sil = float(np.mean(list(per_view.values())))
    return SceneSurvey(
        key=survey_key(dataset, max_frames, blur_px, moving_deg),
        dataset=str(dataset.root or ""),
        body=str(dataset.body_name),
        width=W,
        height=H,
        views=len(sampler.views),
        frames=len(frames),
        joints={name: round(math.degrees(float(r)), 3) for name, r in zip(names, ranges, strict=True)},
        moving_deg=float(moving_deg),
        silhouette_px=round(sil, 1),
        silhouette_fraction=round(sil / (W * H), 5),
        silhouette_px_per_view={k: round(v, 1) for k, v in per_view.items()},
        view_dependence=round(math.sqrt(view_var / max(view_n, 1)), 5),
        pose_dependence=round(math.sqrt(max(total - floor, 0.0)), 5),
        pose_noise=round(math.sqrt(floor), 5),
        skin_offset_px=round(sampler.offset_px / max(sampler.boundary_px, 1.0), 4),
        sampled_frames=sampled,
        seconds=round(time.perf_counter() - t0, 2),
    )


def survey_body(body_node: Any, dataset):
    """The body whose faces and joint names the survey uses: the configured one when it is the dataset's body,
    else the dataset's body with its default options."""
    from framework.build import build_component, node_kwargs

    name, _ = node_kwargs(body_node)
    if name == dataset.body_name:
        return build_component("body", body_node)
    return build_component("body", {"name": dataset.body_name})


def save_survey(survey: SceneSurvey, path: Path) -> None:
    """Write the survey as YAML (atomically, framework.atomic)."""
    import yaml

    atomic_write_text(path, yaml.safe_dump(survey.to_dict(), sort_keys=False))


def load_survey(path: Path) -> SceneSurvey:
    import yaml

    return SceneSurvey.from_dict(yaml.safe_load(Path(path).read_text()))


def cached_survey(
    dataset,
    body,
    max_frames: int = 12,
    blur_px: float = 1.0,
    moving_deg: float = 5.0,
    force: bool = False,
    progress: bool = True,
) -> tuple[SceneSurvey, Path, bool]:
    """The survey of `dataset`, read from beside the data when it was measured before with the same settings.
    Returns (survey, its YAML path, whether it was read from that file)."""
    key = survey_key(dataset, max_frames, blur_px, moving_deg)
    path = survey_path(dataset, key)
    if path.is_file() and not force:
        try:
            survey = load_survey(path)
            if survey.key == key and survey.version == SURVEY_VERSION:
                return survey, path, True
        except (OSError, ValueError, TypeError, KeyError):
            pass  # unreadable or from another version: measure again
    survey = survey_dataset(
        dataset, body, max_frames=max_frames, blur_px=blur_px, moving_deg=moving_deg, progress=progress
    )
    save_survey(survey, path)
    return survey, path, False

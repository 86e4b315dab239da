"""`anny` (the default body): the Anny parametric human (Apache-2.0 code, CC0 MakeHuman data) as a compact asset.

Why an asset: `anny.Anny()` builds an ~800 MB cache in 1-5 min on its first use (0.4-3 s afterwards) and its
phenotype machinery is irrelevant once a body shape is chosen. We run Anny once per (anny version, phenotype), keep
what a skinned avatar needs -- rest mesh, faces, sparse skinning weights, skeleton (parents, rest bone heads, rest
bone poses, reference orientations), UVs -- in `cache_dir()/bodies/anny-<version>-<hash>.npz` (~0.9 MB; one file
serves both skeletons), and every later construction loads that file without importing anny.

Mesh: 13718 vertices, 27420 triangles, Z up, facing -y, the subject's left on +x, ~1.63 m tall, A-pose at rest.

Pose convention (ours, SMPL's): axis-angle per joint, rotation about the rest bone head in world-aligned axes,
composed along the chain. Anny's `local-ref` deltas are world-aligned rotations about the head *in its reference
pose*, whose bone orientations U differ from the rest orientations R by A = U R^T (up to ~0.05 rad here). Our pose
maps exactly to Anny's delta transforms by D_k = A_parent R(θ_k) A_k^T (rotation), d_k = 0, and for the root
D_0 = R(θ_0), d_0 = rest root head (the root's delta is its world pose); see `anny_pose_parameters`. With that,
our forward kinematics + LBS reproduces Anny's own posed vertices to float64 round-off (tests/test_body_anny.py).

Skeletons (constructor `skeleton=`):
- `full`: Anny's 104-bone rig, unchanged.
- `reduced` (default): the 22 bones that matter for a clothed body. Every other bone is folded into its nearest
  kept ancestor (its skinning weights are added to that ancestor), so the reduced body equals the full body posed
  with identity rotations on the folded bones. Joint order (Anny's bone order restricted to the kept bones):

     0 root          (+ pelvis.L, pelvis.R)      11 spine01
     1 upperleg01.L  (+ upperleg02.L)            12 clavicle.L    (+ shoulder01.L)
     2 lowerleg01.L  (+ lowerleg02.L)            13 upperarm01.L  (+ upperarm02.L)
     3 foot.L        (+ toe*.L)                  14 lowerarm01.L  (+ lowerarm02.L)
     4 upperleg01.R  (+ upperleg02.R)            15 wrist.L       (+ metacarpal*.L, finger*.L)
     5 lowerleg01.R  (+ lowerleg02.R)            16 clavicle.R    (+ shoulder01.R)
     6 foot.R        (+ toe*.R)                  17 upperarm01.R  (+ upperarm02.R)
     7 spine05                                   18 lowerarm01.R  (+ lowerarm02.R)
     8 spine04                                   19 wrist.R       (+ metacarpal*.R, finger*.R)
     9 spine03                                   20 neck01        (+ neck02, neck03)
    10 spine02                                   21 head          (+ eye.L, eye.R)

  The twist bones (...02) fold into their segment's main bone (...01), which sits at the anatomical joint (hip,
  knee, shoulder, elbow); `full_pose` expands a reduced pose to the 104-bone rig.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from framework.atomic import atomic_path
from framework.geometry import axis_angle_to_rotmat
from framework.interfaces.body import BodyModel
from framework.paths import cache_dir
from framework.registry import register
from framework.rig.fold import fold_skeleton

ASSET_FORMAT = 1
PHENOTYPE_DEFAULTS = {"gender": 0.5, "age": 0.5, "muscle": 0.5, "weight": 0.5, "height": 0.5, "proportions": 0.5}

# Kept bones of the reduced skeleton (Anny labels), listed in Anny's bone order.
REDUCED_JOINTS: tuple[str, ...] = (
    "root",
    "upperleg01.L",
    "lowerleg01.L",
    "foot.L",
    "upperleg01.R",
    "lowerleg01.R",
    "foot.R",
    "spine05",
    "spine04",
    "spine03",
    "spine02",
    "spine01",
    "clavicle.L",
    "upperarm01.L",
    "lowerarm01.L",
    "wrist.L",
    "clavicle.R",
    "upperarm01.R",
    "lowerarm01.R",
    "wrist.R",
    "neck01",
    "head",
)


def anny_version() -> str:
    try:
        return importlib.metadata.version("anny")
    except importlib.metadata.PackageNotFoundError:
        return "none"


def _requires() -> str | None:
    if importlib.util.find_spec("anny") is None:
        return "the `anny` package is not installed (pip install anny)"
    return None


def _phenotype(**kwargs: float) -> dict[str, float]:
    unknown = set(kwargs) - set(PHENOTYPE_DEFAULTS)
    if unknown:
        raise ValueError(
            f"anny body: unknown phenotype keys {sorted(unknown)}; expected a subset of {sorted(PHENOTYPE_DEFAULTS)}."
        )
    ph = {k: float(kwargs.get(k, v)) for k, v in PHENOTYPE_DEFAULTS.items()}
    for k, v in ph.items():
        if not 0.0 <= v <= 1.0:
            raise ValueError(f"anny body: phenotype '{k}' = {v} is outside [0, 1]; Anny's phenotypes are in 0..1.")
    return ph


def asset_path(phenotype: dict[str, float], root: Path | None = None) -> Path:
    """Where the compact asset of this anny version and phenotype lives."""
    key = json.dumps({"format": ASSET_FORMAT, "phenotype": phenotype}, sort_keys=True)
    digest = hashlib.sha1(key.encode()).hexdigest()[:12]
    return (root or cache_dir() / "bodies") / f"anny-{anny_version()}-{digest}.npz"


def build_anny_asset(phenotype: dict[str, float], path: Path) -> None:
    """Run Anny once and write the compact asset to `path` (atomically, so concurrent builders cannot clash)."""
    msg = (
        f"building the Anny body asset once (1-5 min, ~1.7 GB RAM; anny's own cache goes to ~/.cache/anny "
        f"or $ANNY_CACHE_DIR) -> {path}"
    )
    print(msg, file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    import anny  # lazy: heavy, and only needed once

    model = anny.Anny()  # float64, rig 'anny' (104 bones), topology 'anny', pose parameterisation 'local-ref'
    with torch.no_grad():
        out = model(phenotype_kwargs=phenotype)
    if model.reference_bone_orientations is not None:
        ref = model.reference_bone_orientations.detach()
    else:
        ref = out["rest_bone_poses"][0, :, :3, :3]
    arrays = {
        "rest_vertices": out["rest_vertices"][0].double().numpy(),  # [V, 3]
        "faces": model.get_triangular_faces().numpy().astype(np.int32),  # [F, 3]
        "bone_indices": model.vertex_bone_indices.numpy().astype(np.int16),  # [V, 9]
        "bone_weights": model.vertex_bone_weights.double().numpy(),  # [V, 9]
        "parents": np.asarray(model.bone_parents, dtype=np.int64),  # [104]
        "bone_labels": np.asarray(model.bone_labels),
        "rest_joints": out["rest_bone_heads"][0].double().numpy(),  # [104, 3]
        "rest_bone_poses": out["rest_bone_poses"][0].double().numpy(),  # [104, 4, 4]
        "reference_orientations": ref.double().numpy(),  # [104, 3, 3]
        "uvs": model.texture_coordinates.float().numpy(),  # [Vt, 2]
        "face_uvs": model.face_texture_coordinate_indices.numpy().astype(np.int32),  # [F, 3]
        "meta": np.asarray(json.dumps({"anny": anny_version(), "phenotype": phenotype, "format": ASSET_FORMAT})),
    }
    with atomic_path(path) as tmp:  # a build killed half-way leaves no asset that looks complete
        np.savez_compressed(tmp, **arrays)
    print(f"Anny body asset written in {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)


def load_anny_asset(phenotype: dict[str, float] | None = None, root: Path | None = None) -> dict[str, np.ndarray]:
    """The compact asset as numpy arrays (float64 geometry), building it first if it is not cached."""
    phenotype = _phenotype(**(phenotype or {}))
    path = asset_path(phenotype, root)
    if not path.exists():
        reason = _requires()
        if reason is not None:
            raise RuntimeError(f"anny body: no cached asset at {path} and cannot build it: {reason}.")
        build_anny_asset(phenotype, path)
    with np.load(path, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


def anny_pose_parameters(
    pose: Tensor,
    rest_bone_poses: Tensor,
    reference_orientations: Tensor,
    rest_joints: Tensor,
    parents: Tensor | list[int],
) -> Tensor:
    """Our full-rig axis-angle pose [B, J, 3] -> Anny `local-ref` delta transforms [B, J, 4, 4] giving the same mesh.

    With rest orientations R, reference orientations U and A = U R^T: D_k = A_parent R(θ_k) A_k^T, d_k = 0 for
    non-root bones; the root's delta is its world pose, D_0 = R_0 R(θ_0), d_0 = U_0 h_0 (Anny's root has
    U_0 = R_0 = I, so D_0 = R(θ_0), d_0 = h_0). Anny offsets the root's children in the root's rest frame, so the
    two conventions agree only when the root's reference orientation equals its rest orientation (checked)."""
    dtype = pose.dtype
    R_rest = rest_bone_poses[..., :3, :3].to(dtype)  # [J, 3, 3]
    U = reference_orientations.to(dtype)  # [J, 3, 3]
    if not torch.allclose(U[0], R_rest[0], atol=1e-6):
        raise ValueError(
            "anny pose conversion: the root's reference orientation differs from its rest orientation; "
            "Anny's `local-ref` root then has no SMPL-style equivalent."
        )
    A = U @ R_rest.transpose(-1, -2)  # [J, 3, 3]
    par = torch.as_tensor(parents, dtype=torch.long).clamp_min(0)
    Rt = axis_angle_to_rotmat(pose)  # [B, J, 3, 3]
    D = A[par] @ Rt @ A.transpose(-1, -2)  # [B, J, 3, 3]
    D0 = R_rest[0] @ Rt[:, 0]  # [B, 3, 3]
    D = torch.cat([D0.unsqueeze(1), D[:, 1:]], dim=1)
    delta = torch.zeros(*D.shape[:2], 4, 4, dtype=dtype, device=D.device)
    delta[..., :3, :3] = D
    delta[..., 3, 3] = 1.0
    delta[:, 0, :3, 3] = U[0] @ rest_joints[0].to(dtype)
    return delta


@register("body", "anny", requires=_requires)
class AnnyBody(BodyModel):
    """Anny body from the compact cached asset; `skeleton` "reduced" (22 bones, default) or "full" (104 bones)."""

    def __init__(
        self,
        skeleton: str = "reduced",
        gender: float = 0.5,
        age: float = 0.5,
        muscle: float = 0.5,
        weight: float = 0.5,
        height: float = 0.5,
        proportions: float = 0.5,
    ) -> None:
        super().__init__()
        if skeleton not in ("reduced", "full"):
            raise ValueError(f"anny body: skeleton must be 'reduced' or 'full'; got {skeleton!r}.")
        self.skeleton = skeleton
        self.phenotype = _phenotype(
            gender=gender, age=age, muscle=muscle, weight=weight, height=height, proportions=proportions
        )
        a = load_anny_asset(self.phenotype)
        labels = [str(x) for x in a["bone_labels"]]
        full_parents = [int(p) for p in a["parents"]]
        V, J_full = a["rest_vertices"].shape[0], len(labels)
        dense = np.zeros((V, J_full))
        np.add.at(dense, (np.arange(V)[:, None], a["bone_indices"].astype(np.int64)), a["bone_weights"])
        if skeleton == "full":
            kept, parents, to_reduced = list(range(J_full)), full_parents, list(range(J_full))
        else:
            kept, parents, to_reduced = fold_skeleton(labels, full_parents, REDUCED_JOINTS, owner="anny body")
        weights = np.zeros((V, len(kept)))
        np.add.at(weights.T, np.asarray(to_reduced), dense.T)  # fold: sum weights of folded bones into ancestors
        self.joint_names = [labels[i] for i in kept]
        self.full_joint_names = labels
        f32 = torch.float32
        self.register_buffer("rest_vertices", torch.as_tensor(a["rest_vertices"], dtype=f32))  # [V, 3]
        self.register_buffer("faces", torch.as_tensor(a["faces"], dtype=torch.long))  # [F, 3]
        self.register_buffer("skin_weights", torch.as_tensor(weights, dtype=f32))  # [V, J]
        self.register_buffer("parents", torch.as_tensor(parents, dtype=torch.long))  # [J]
        self.register_buffer("rest_joints", torch.as_tensor(a["rest_joints"][kept], dtype=f32))  # [J, 3]
        self.register_buffer("uvs", torch.as_tensor(a["uvs"], dtype=f32))  # [Vt, 2]
        self.register_buffer("face_uvs", torch.as_tensor(a["face_uvs"], dtype=torch.long))  # [F, 3]
        # full rig index -> joint of this body that drives it (identity map for the full skeleton)
        self.register_buffer("full_to_reduced", torch.as_tensor(to_reduced, dtype=torch.long), persistent=False)
        self.register_buffer("kept_full_indices", torch.as_tensor(kept, dtype=torch.long), persistent=False)

    def pose_description(self) -> str:
        return f"anny body ({self.skeleton} skeleton, {self.num_joints} joints: see joint_names)"

    def full_pose(self, pose: Tensor) -> Tensor:
        """This body's pose [B, J, 3] -> the full 104-bone pose [B, 104, 3] with identity on folded bones."""
        full = pose.new_zeros(pose.shape[0], len(self.full_joint_names), 3)
        full[:, self.kept_full_indices] = pose
        return full

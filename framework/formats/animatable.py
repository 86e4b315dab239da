"""The animatable avatar package: canonical Gaussians + skinning data + per-frame bone transforms, for any engine.

`python -m framework.export ckpt=... pose=<motion> animatable=true` writes a folder:

    <name>/
      canonical.ply   the canonical (rest-pose) Gaussians in the 3DGS PLY layout (framework.formats.splat_ply)
      rig.npz         everything needed to pose them (numpy .npz, float32 unless stated):
        format             str, "splatrig-animatable-2" ("-1": a package written before `centres`, read as blended)
        skin_weights       [N, J]  blend weights per Gaussian, in canonical.ply's vertex order (rows sum to 1, except
                           for the paper's additive residual w0 + F_dw, which nothing renormalises: about 1)
        parents            [J] int32, parent joint of each joint (-1 for the root)
        joint_names        [J] str
        rest_joints        [J, 3]  rest joint positions (the skeleton the transforms were made with)
        bone_transforms    [F, J, 4, 4]  rest-to-world skinning transform T_fk of joint k in frame f (world =
                           splatrig's, Z up; the root transform is included, so no other placement is needed)
        poses              [F, J, 3]  the axis-angle joint rotations that produced them (informative)
        fps                float, frames per second of the F frames
        stretch            str, "diag" or "none" (step 4 below)
        centres            str, "rigid" or "blended" (step 3 below)
        sh_degree          int, the SH degree the avatar renders with
        Present only when the avatar has a pose-dependent appearance corrector (the paper's F_a), which an engine
        cannot evaluate: its output per frame, i.e. the corrected canonical attributes
        corrected_opacity_logits [F, N], corrected_log_scales [F, N, 3], corrected_quats [F, N, 4] (wxyz),
        corrected_sh       [F, N, Kc, 3]: replaces the first Kc SH coefficients (Kc = 1: the DC term only)
      README.md       this description

Posing frame f (what `pose_frame` does; tests/test_animatable_package.py checks it against an independent numpy
implementation and the avatar's own render):
  1. Start from canonical.ply: means x_i, quaternions q_i, log scales s_i, opacity logits o_i, SH c_i. With the
     corrected_* arrays, replace q_i, s_i, o_i and the first Kc SH coefficients by frame f's values (means never
     change).
  2. Blend: [A_i | t_i] = sum_k skin_weights[i, k] * T_fk[:3, :]  (3x3 A_i, 3-vector t_i).
  3. Polar decomposition A_i = R_i S_i (R_i a rotation, S_i symmetric; R_i = U V^T from the SVD A_i = U D V^T).
     Mean: with centres = "rigid" (the paper's eq. 4), x'_i = R_i x_i + t_i; with "blended", x'_i = A_i x_i + t_i.
  4. Rotation: q'_i = quat(R_i) * q_i (Hamilton product). Scale: with stretch = "diag", s'_il = s_il +
     log(max(a_l^T S_i a_l, 1e-4)), a_l = the l-th column of the rotation matrix of q_i; with "none", s'_i = s_i.
  5. SH: coefficients of degree l rotate with R_i (colour seen from direction R_i d after posing equals colour from d
     before); degree 1 is the vector v = (-c_3, -c_1, c_2) per channel turning into R_i v, degrees 2 and 3 by the
     corresponding Wigner matrices (framework.rig.sh_rotation). Opacity is unchanged.
  6. Render as 3DGS does: colour = SH_C0 * dc + ... + 0.5 clamped at 0, opacity = sigmoid(o), scales = exp(s').
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from framework.atomic import atomic_path
from framework.errors import SplatrigError
from framework.formats.splat_ply import read_splat_ply, write_splat_ply
from framework.types import Gaussians

FORMAT = "splatrig-animatable-2"
#: formats this reader accepts -> the centres of a package that does not state them (version 1: always blended)
READABLE = {FORMAT: None, "splatrig-animatable-1": "blended"}
CENTRES = ("rigid", "blended")
CANONICAL = "canonical.ply"
RIG = "rig.npz"
CORRECTED_KEYS = ("corrected_opacity_logits", "corrected_log_scales", "corrected_quats", "corrected_sh")


class PackageError(SplatrigError, ValueError):
    """An animatable package is incomplete or inconsistent; the message names the file and the problem."""


@dataclass
class AnimatablePackage:
    canonical: Gaussians  # N Gaussians in the rest pose
    skin_weights: np.ndarray  # [N, J]
    parents: np.ndarray  # [J]
    joint_names: list[str]
    rest_joints: np.ndarray  # [J, 3]
    bone_transforms: np.ndarray  # [F, J, 4, 4]
    poses: np.ndarray  # [F, J, 3]
    fps: float
    stretch: str
    sh_degree: int
    corrections: dict[str, np.ndarray] | None  # CORRECTED_KEYS -> [F, N, ...], or None
    centres: str = "blended"  # step 3: "rigid" (R x + t) or "blended" (A x + t), as the avatar's deformer posed them

    @property
    def num_frames(self) -> int:
        return int(self.bone_transforms.shape[0])


def write_package(out_dir: str | os.PathLike, package: AnimatablePackage) -> Path:
    """Write canonical.ply, rig.npz and README.md into `out_dir` (each file atomically)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_splat_ply(out / CANONICAL, package.canonical)
    arrays: dict[str, np.ndarray] = {
        "format": np.asarray(FORMAT),
        "skin_weights": np.asarray(package.skin_weights, dtype=np.float32),
        "parents": np.asarray(package.parents, dtype=np.int32),
        "joint_names": np.asarray(package.joint_names, dtype=str),
        "rest_joints": np.asarray(package.rest_joints, dtype=np.float32),
        "bone_transforms": np.asarray(package.bone_transforms, dtype=np.float32),
        "poses": np.asarray(package.poses, dtype=np.float32),
        "fps": np.asarray(float(package.fps)),
        "stretch": np.asarray(package.stretch),
        "centres": np.asarray(package.centres),
        "sh_degree": np.asarray(int(package.sh_degree)),
    }
    for key, value in (package.corrections or {}).items():
        arrays[key] = np.asarray(value, dtype=np.float32)
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    _atomic_write(out / RIG, buffer.getvalue())
    _atomic_write(out / "README.md", (__doc__ or "").encode())
    return out


def _atomic_write(path: Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def read_package(path: str | os.PathLike) -> AnimatablePackage:
    """Read a package folder written by `write_package`."""
    root = Path(path)
    for name in (CANONICAL, RIG):
        if not (root / name).is_file():
            raise PackageError(f"{root}: missing {name}; an animatable package holds {CANONICAL} and {RIG}.")
    with np.load(root / RIG, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    fmt = str(arrays.get("format", ""))
    if fmt not in READABLE:
        raise PackageError(f"{root / RIG}: format is {arrays.get('format')!r}, expected one of {sorted(READABLE)}.")
    centres = str(arrays["centres"]) if "centres" in arrays else READABLE[fmt]
    if centres not in CENTRES:
        raise PackageError(f"{root / RIG}: centres is {centres!r}, expected one of {CENTRES}.")
    canonical = read_splat_ply(root / CANONICAL)
    n, j = arrays["skin_weights"].shape
    if n != canonical.num or arrays["bone_transforms"].shape[1:] != (j, 4, 4):
        raise PackageError(
            f"{root}: {canonical.num} Gaussians in {CANONICAL}, skin_weights {arrays['skin_weights'].shape}, "
            f"bone_transforms {arrays['bone_transforms'].shape}; expected [N, J] and [F, J, 4, 4] with matching N, J."
        )
    corrections = {k: arrays[k] for k in CORRECTED_KEYS if k in arrays} or None
    return AnimatablePackage(
        canonical=canonical,
        skin_weights=arrays["skin_weights"],
        parents=arrays["parents"],
        joint_names=[str(x) for x in arrays["joint_names"]],
        rest_joints=arrays["rest_joints"],
        bone_transforms=arrays["bone_transforms"],
        poses=arrays["poses"],
        fps=float(arrays["fps"]),
        stretch=str(arrays["stretch"]),
        sh_degree=int(arrays["sh_degree"]),
        corrections=corrections,
        centres=centres,
    )


def corrected_canonical(package: AnimatablePackage, frame: int) -> Gaussians:
    """Step 1 of the module docstring: the canonical Gaussians with frame `frame`'s corrections applied."""
    g = package.canonical
    if package.corrections is None:
        return g
    c = {k: torch.from_numpy(np.asarray(v[frame])).to(g.means.device) for k, v in package.corrections.items()}
    sh_c = c["corrected_sh"]  # [N, Kc, 3]
    sh = torch.cat([sh_c, g.sh[:, sh_c.shape[1] :]], dim=1)
    return g.replace(
        opacity_logits=c["corrected_opacity_logits"],
        log_scales=c["corrected_log_scales"],
        quats=c["corrected_quats"],
        sh=sh,
    )


def pose_frame(package: AnimatablePackage, frame: int) -> Gaussians:
    """Steps 1-5 of the module docstring for frame `frame`: world-space Gaussians ready to rasterise."""
    from framework.rig.lbs import apply_lbs

    if not 0 <= frame < package.num_frames:
        raise PackageError(f"frame {frame} is outside the package's {package.num_frames} frames.")
    device = package.canonical.means.device
    weights = torch.from_numpy(np.asarray(package.skin_weights, dtype=np.float32)).to(device)
    transforms = torch.from_numpy(np.asarray(package.bone_transforms[frame], dtype=np.float32)).to(device)
    return apply_lbs(corrected_canonical(package, frame), weights, transforms, package.stretch, centres=package.centres)

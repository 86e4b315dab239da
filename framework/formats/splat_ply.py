"""Gaussians as a standard 3D Gaussian splatting PLY: the layout of graphdeco-inria's `GaussianModel.save_ply`.

Why this layout: every splat viewer and tool (SuperSplat, the antimatter15 / gsplat.js viewers, nerfstudio, Unity and
Unreal importers) reads exactly it. One binary little-endian `vertex` element with these float32 properties, in order:

    x y z                 mean (metres; splatrig's world: Z up)
    nx ny nz              zeros (3DGS writes zeros; viewers ignore them)
    f_dc_0 f_dc_1 f_dc_2  SH degree-0 coefficient of R, G, B (colour = 0.28209479 * f_dc + 0.5 towards any view)
    f_rest_0 .. f_rest_44 SH coefficients 1..15, CHANNEL-MAJOR: f_rest_{c * 15 + (k - 1)} is coefficient k of colour
                          channel c (3DGS stores features_rest [N, 15, 3] and writes it transposed to [N, 3, 15]).
                          A model of SH degree d < 3 is zero-padded per channel (coefficients k >= (d + 1)^2 are 0),
                          so every file has all 45, which is what viewers expect
    opacity               logit (the value before the sigmoid)
    scale_0 scale_1 scale_2  log of the standard deviations along the Gaussian's axes
    rot_0 rot_1 rot_2 rot_3  quaternion w x y z (rot_0 is the real part), not necessarily normalised

These are exactly our raw parameters (`framework.types.Gaussians`), so writing and reading are lossless for float32
values and a read-back file renders bit-identically. Reading also accepts the unpadded files 3DGS writes for lower
degrees (3 * ((d + 1)^2 - 1) f_rest properties).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from framework.atomic import atomic_path
from framework.errors import SplatrigError
from framework.types import Gaussians

MAX_SH_DEGREE = 3
REST_PER_CHANNEL = (MAX_SH_DEGREE + 1) ** 2 - 1  # 15


class SplatFileError(SplatrigError, ValueError):
    """A PLY file is not in the 3DGS layout; the message names the file, what was expected and what was found."""


def ply_attribute_names(rest_per_channel: int = REST_PER_CHANNEL) -> list[str]:
    """The 3DGS vertex properties in file order (62 for the padded degree-3 layout)."""
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * rest_per_channel)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def gaussians_to_vertex_array(gaussians: Gaussians) -> np.ndarray:
    """Structured float32 array [N] in the 3DGS layout (SH zero-padded to degree 3)."""
    sh = gaussians.sh.detach().float().cpu()  # [N, K, 3]
    n, k = sh.shape[0], sh.shape[1]
    if k > REST_PER_CHANNEL + 1:
        raise ValueError(f"splat PLY: {k} SH coefficients per channel; the 3DGS layout holds at most 16 (degree 3).")
    rest = torch.zeros(n, REST_PER_CHANNEL, 3)
    rest[:, : k - 1] = sh[:, 1:]
    columns = [
        gaussians.means.detach().float().cpu(),  # [N, 3]
        torch.zeros(n, 3),  # normals
        sh[:, 0],  # [N, 3]
        rest.transpose(1, 2).reshape(n, 3 * REST_PER_CHANNEL),  # [N, 45] channel-major
        gaussians.opacity_logits.detach().float().cpu().reshape(n, 1),
        gaussians.log_scales.detach().float().cpu(),  # [N, 3]
        gaussians.quats.detach().float().cpu(),  # [N, 4] wxyz
    ]
    flat = torch.cat(columns, dim=1).numpy()  # [N, 62]
    names = ply_attribute_names()
    out = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        out[name] = flat[:, i]
    return out


def write_splat_ply(path: str | os.PathLike, gaussians: Gaussians) -> Path:
    """Write `gaussians` as a binary 3DGS PLY (atomically: a partial file never takes the name)."""
    from plyfile import PlyData, PlyElement

    path = Path(path)
    element = PlyElement.describe(gaussians_to_vertex_array(gaussians), "vertex")
    with atomic_path(path) as tmp:
        PlyData([element], text=False, byte_order="<").write(str(tmp))
    return path


def read_splat_ply(path: str | os.PathLike) -> Gaussians:
    """Gaussians from a 3DGS PLY: sh [N, (d + 1)^2, 3] with d from the number of f_rest properties (3 when padded)."""
    from plyfile import PlyData

    path = Path(path)
    if not path.is_file():
        raise SplatFileError(f"{path}: no such file; expected a 3D Gaussian splatting PLY.")
    ply = PlyData.read(str(path))
    if "vertex" not in [e.name for e in ply.elements]:
        raise SplatFileError(f"{path}: has no 'vertex' element; expected the 3DGS layout (x, y, z, f_dc_0, ...).")
    vertex = ply["vertex"]
    present = {p.name for p in vertex.properties}
    n_rest = sum(1 for name in present if name.startswith("f_rest_"))
    degree = next((d for d in range(MAX_SH_DEGREE + 1) if 3 * ((d + 1) ** 2 - 1) == n_rest), None)
    if degree is None:
        raise SplatFileError(f"{path}: {n_rest} f_rest properties; expected 0, 9, 24 or 45 (SH degree 0..3).")
    per_channel = (degree + 1) ** 2 - 1
    missing = [name for name in ply_attribute_names(per_channel) if name not in present and name[0] != "n"]
    if missing:
        raise SplatFileError(
            f"{path}: missing vertex properties {missing[:6]}; expected the 3DGS layout "
            f"(x y z, f_dc_0..2, f_rest_*, opacity, scale_0..2, rot_0..3)."
        )

    def cols(*names: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.asarray(vertex[name], dtype=np.float32) for name in names], axis=1))

    n = len(vertex.data)
    dc = cols("f_dc_0", "f_dc_1", "f_dc_2").reshape(n, 1, 3)
    rest = cols(*[f"f_rest_{i}" for i in range(3 * per_channel)]).reshape(n, 3, per_channel).transpose(1, 2)
    return Gaussians(
        means=cols("x", "y", "z"),
        quats=cols("rot_0", "rot_1", "rot_2", "rot_3"),
        log_scales=cols("scale_0", "scale_1", "scale_2"),
        opacity_logits=cols("opacity").reshape(n),
        sh=torch.cat([dc, rest], dim=1).contiguous(),
    )

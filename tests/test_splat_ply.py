"""The 3DGS PLY export: the original attribute layout, lossless read-back, an identical render after a round trip."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement
from trained_avatar import load_tiny

from framework.formats.splat_ply import SplatFileError, read_splat_ply, write_splat_ply
from framework.types import Gaussians

# graphdeco-inria GaussianModel.construct_list_of_attributes for max_sh_degree = 3, written out by hand
EXPECTED = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    + [f"f_rest_{i}" for i in range(45)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)


def random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    return Gaussians(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 3,
        opacity_logits=torch.randn(n, generator=g) * 5,
        sh=torch.randn(n, (degree + 1) ** 2, 3, generator=g),
    )


@pytest.fixture(scope="module")
def tiny(tiny_avatar):
    return tiny_avatar


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_file_has_the_original_3dgs_layout(tmp_path, degree):
    g = random_gaussians(7, degree)
    path = write_splat_ply(tmp_path / "a.ply", g)
    ply = PlyData.read(str(path))
    assert [e.name for e in ply.elements] == ["vertex"]
    vertex = ply["vertex"]
    assert [p.name for p in vertex.properties] == EXPECTED
    assert all(vertex.data.dtype[name] == np.dtype("<f4") for name in EXPECTED)
    assert not ply.text  # binary, as 3DGS writes
    k_used = (degree + 1) ** 2
    for i in range(7):
        row = vertex.data[i]
        assert [row["x"], row["y"], row["z"]] == pytest.approx(g.means[i].tolist())
        assert [row["nx"], row["ny"], row["nz"]] == [0.0, 0.0, 0.0]
        for c in range(3):
            assert row[f"f_dc_{c}"] == pytest.approx(float(g.sh[i, 0, c]))
            for k in range(1, 16):  # channel-major: f_rest_{c * 15 + k - 1} is coefficient k of channel c
                expected = float(g.sh[i, k, c]) if k < k_used else 0.0
                assert row[f"f_rest_{c * 15 + k - 1}"] == pytest.approx(expected)
        assert row["opacity"] == pytest.approx(float(g.opacity_logits[i]))  # a logit, as stored
        assert [row[f"scale_{j}"] for j in range(3)] == pytest.approx(g.log_scales[i].tolist())  # logs
        assert [row[f"rot_{j}"] for j in range(4)] == pytest.approx(g.quats[i].tolist())  # w x y z


def test_read_back_is_lossless(tmp_path):
    g = random_gaussians(50, 3, seed=1)
    back = read_splat_ply(write_splat_ply(tmp_path / "a.ply", g))
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert torch.equal(getattr(back, name), getattr(g, name)), name


def test_reads_the_unpadded_files_3dgs_writes_for_lower_degrees(tmp_path):
    """3DGS trained with max_sh_degree = 1 writes 9 f_rest values (3 channels x 3 coefficients), channel-major."""
    g = random_gaussians(5, 1, seed=2)
    rest = g.sh[:, 1:].transpose(1, 2).reshape(5, 9)  # [N, 3 channels x 3 coefficients]
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(9)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    cols = torch.cat(
        [g.means, torch.zeros(5, 3), g.sh[:, 0], rest, g.opacity_logits[:, None], g.log_scales, g.quats], dim=1
    ).numpy()
    data = np.empty(5, dtype=[(n, "f4") for n in names])
    for i, n in enumerate(names):
        data[n] = cols[:, i]
    PlyData([PlyElement.describe(data, "vertex")]).write(str(tmp_path / "low.ply"))
    back = read_splat_ply(tmp_path / "low.ply")
    assert back.sh.shape == (5, 4, 3)
    assert torch.equal(back.sh, g.sh)


def test_a_ply_that_is_not_3dgs_is_refused_by_name(tmp_path):
    data = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    PlyData([PlyElement.describe(data, "vertex")]).write(str(tmp_path / "points.ply"))
    with pytest.raises(SplatFileError, match="points.ply"):
        read_splat_ply(tmp_path / "points.ply")


def test_posed_avatar_renders_identically_after_a_round_trip(tiny, tmp_path, monkeypatch):
    """Export a posed frame, read it back and rasterise it: the image equals the render of the exported Gaussians bit
    for bit, and the avatar's own render to float rounding (the avatar evaluates the colour at R^T d for one camera
    instead of rotating the coefficients the PLY stores: the same colour by another order of operations)."""
    from framework.animation.frames import frame_batch, posed_gaussians
    from framework.animation.sources import load_motion
    from framework.registry import RASTERIZERS

    ckpt, cache = tiny
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(cache))
    module, dm = load_tiny(ckpt)
    motion, frames = load_motion(module, dm, "train")
    pose, root = torch.as_tensor(motion.poses[2]), torch.as_tensor(motion.roots[2])
    posed = posed_gaussians(module, pose, root, frames[2])
    assert posed.sh[:, 1:4].abs().sum() > 0  # degree-1 SH is present, so f_rest ordering matters
    back = read_splat_ply(write_splat_ply(tmp_path / "posed.ply", posed))

    cams = dm.split("novel_view").cameras.index(0)
    degree = module.sh_degree(module.trained_steps())
    assert degree == 3
    with torch.no_grad():
        ours = module.render_batch(frame_batch(cams, pose, root, frames[2])).render.rgb
        raster = RASTERIZERS.build("torch_ref")
        theirs, exported = (
            raster.render(
                g.means,
                g.quats,
                torch.exp(g.log_scales),
                torch.sigmoid(g.opacity_logits),
                g.sh,
                cams,
                sh_degree=degree,
                background=module.avatar.background,
            ).rgb
            for g in (back, posed)
        )
    assert ours.abs().sum() > 0
    assert torch.equal(theirs, exported)
    torch.testing.assert_close(theirs, ours, atol=1e-5, rtol=0)

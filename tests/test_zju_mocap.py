"""Dataset `zju_mocap`: cameras that reproject the stored geometry, K under downscaling and undistortion, the root
convention with a real body model, protocols and splits, caches, and one test per kind of bad input."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from test_zju_format import centroid, project, ring_cameras, write_core313_by_hand, write_toy_sequence

from framework.data.boundary import boundary_mask
from framework.data.zju.dataset import ZjuMocapDataset
from framework.data.zju.layout import ZjuFormatError, zju_camera_names
from framework.data.zju.reader import ZjuSequence, check_body_compatible
from framework.data.zju.writer import ZjuWriter
from framework.geometry import axis_angle_to_rotmat
from plugins.body.procedural import ProceduralBody


@pytest.fixture(scope="module")
def body() -> ProceduralBody:
    return ProceduralBody(segments=8)


def write_body_sequence(root: Path, body: ProceduralBody, C: int = 4, F: int = 3, size: int = 96, seed: int = 0):
    """Posed procedural body per frame: world vertices = R(Rh) LBS(pose) + Th; masks are its projected triangles."""
    g = torch.Generator().manual_seed(seed)
    J = body.num_joints
    K, R, T = ring_cameras(C, radius=3.5, size=size, f=60.0, seed=seed)
    w = ZjuWriter(root, zju_camera_names(C), image_ext=".png")
    w.write_cameras(K, None, R, T)
    faces = body.faces.numpy()
    out = []
    for f in range(F):
        pose = torch.randn(1, J, 3, generator=g) * 0.25
        Rh = torch.randn(1, 3, generator=g) * 0.4
        Th = torch.randn(1, 3, generator=g) * 0.1
        local = body.posed_vertices(pose)[0].double()  # [V, 3]
        verts = (local @ axis_angle_to_rotmat(Rh.double())[0].T + Th.double()).numpy()
        images = np.zeros((C, size, size, 3), np.uint8)
        masks = np.zeros((C, size, size), np.uint8)
        for c in range(C):
            uv = project(K[c], R[c], T[c], verts)  # splatrig convention
            tris = np.round((uv[faces] - 0.5) * 16).astype(np.int32)  # cv2 pixel centres are integers; 4 bits
            cv2.fillPoly(masks[c], list(tris), 1, lineType=cv2.LINE_8, shift=4)
            images[c][masks[c] > 0] = (200, 120, (40 + 50 * c) % 256)
        params = {"poses": pose.numpy().reshape(1, -1), "Rh": Rh.numpy(), "Th": Th.numpy(), "body": "procedural"}
        w.write_frame(f, images, masks, params, verts)
        out.append(verts)
    w.finish()
    return out


# ------------------------------------------------------------------------------------------------ geometry
@pytest.mark.parametrize("downscale", [1, 2])
def test_vertices_reproject_into_masks_and_root_convention(tmp_path: Path, body: ProceduralBody, downscale: int):
    verts = write_body_sequence(tmp_path, body)
    ds = ZjuMocapDataset(str(tmp_path), protocol=None, downscale=downscale, boundary_px=2)
    assert ds.body_name == "procedural" and len(ds) == 3 * 4
    check_body_compatible(ds, body)  # same joint count: no error
    inside = total = 0
    for i in range(len(ds)):
        b = ds[i]
        f = int(b.frame[0])
        # EasyMocap root: world = R(Rh) M(pose) + Th, with FrameBatch.root = [[R(Rh), Th], [0, 1]]
        local = body.posed_vertices(b.pose)[0]
        world = local @ b.root[0, :3, :3].T + b.root[0, :3, 3]
        np.testing.assert_allclose(world.numpy(), verts[f], atol=2e-5)
        # projected stored vertices land inside the mask
        cam = b.cameras
        X = torch.from_numpy(verts[f]).float()
        p = X @ cam.world_to_cam[0, :3, :3].T + cam.world_to_cam[0, :3, 3]
        uv = (p @ cam.K[0].T)[:, :2] / p[:, 2:3]
        j = uv[:, 0].floor().long().clamp(0, cam.width - 1)
        ii = uv[:, 1].floor().long().clamp(0, cam.height - 1)
        inside += int((b.mask[0, ii, j] > 0).sum())
        total += len(j)
        assert b.image.shape == (1, 96 // downscale, 96 // downscale, 3) and b.image.dtype == torch.float32
    assert inside / total >= 0.99, inside / total


def distort_normalized(xy: np.ndarray, D: np.ndarray) -> np.ndarray:
    """OpenCV's (Brown-Conrady) model on normalised coordinates [N, 2], float64."""
    k1, k2, p1, p2, k3 = D
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    return np.stack(
        [x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y], -1
    )


def undistort_points(uv: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Inverse of the distortion by fixed-point iteration (an independent reference for cv2's remap)."""
    xd = (uv - K[:2, 2]) / np.diag(K)[:2]
    x = xd.copy()
    for _ in range(200):
        x = x + (xd - distort_normalized(x, D))
    assert np.abs(distort_normalized(x, D) - xd).max() < 1e-9
    return x * np.diag(K)[:2] + K[:2, 2]


@pytest.mark.parametrize("downscale", [1, 2, 4])
def test_marker_reprojection_with_downscale(tmp_path: Path, downscale: int) -> None:
    """Sub-pixel check of the pixel-centre convention: a blob drawn at the written projection has its centroid at the
    loader's projection, at every downscale (a half-pixel mistake would show as 0.25..0.5 px)."""
    gt = write_toy_sequence(tmp_path, C=3, F=2, size=64)
    ds = ZjuMocapDataset(str(tmp_path), protocol=None, downscale=downscale, mask_background=False)
    for i in range(len(ds)):
        b = ds[i]
        f = int(b.frame[0])
        K = b.cameras.K[0].double().numpy()
        w2c = b.cameras.world_to_cam[0].double().numpy()
        uv = project(K, w2c[:3, :3], w2c[:3, 3], gt["markers"][f : f + 1])[0]
        found = centroid(b.image[0, ..., 0].double().numpy())
        assert np.abs(found - uv).max() < 0.03, (downscale, found, uv)


def test_downscale_K_formula(tmp_path: Path) -> None:
    write_toy_sequence(tmp_path, C=2, F=1, size=64)
    full = ZjuMocapDataset(str(tmp_path), protocol=None)
    third = ZjuMocapDataset(str(tmp_path), protocol=None, downscale=3)
    assert (third.width, third.height) == (21, 21)
    K, K3 = full.cameras.K.double(), third.cameras.K.double()
    s = 21 / 64
    torch.testing.assert_close(K3[:, :2, :], K[:, :2, :] * s, rtol=1e-6, atol=1e-5)
    # in OpenCV's convention the same map is cx' = (cx_cv + 0.5) * s - 0.5
    seq = ZjuSequence(tmp_path)
    torch.testing.assert_close(
        K3[:, 0, 2] - 0.5, torch.from_numpy((seq.cameras.K[:, 0, 2] + 0.5) * s - 0.5), rtol=0, atol=1e-5
    )
    assert third[0].image.shape == (1, 21, 21, 3)


def test_undistortion_keeps_K_and_moves_pixels(tmp_path: Path) -> None:
    """Images are stored distorted; the loader undistorts them (cv2.undistort semantics) and K stays as stored."""
    C, size = 2, 64
    K, R, T = ring_cameras(C, size=size, f=70.0)
    D = np.array([[-0.2, 0.03, 0.002, -0.001, 0.0], [0.2, -0.03, 0.0, 0.002, 0.0]])
    w = ZjuWriter(tmp_path, zju_camera_names(C), image_ext=".png")
    w.write_cameras(K, D, R, T)
    X = np.array([[0.7, -0.7, 0.7]])
    Kcv = K.copy()
    Kcv[:, :2, 2] -= 0.5
    imgs = []
    jj, ii = np.meshgrid(np.arange(size, dtype=np.float64), np.arange(size, dtype=np.float64))
    pix = np.stack([jj.ravel(), ii.ravel()], -1)[:, None, :]  # OpenCV pixel centres [HW, 1, 2]
    for c in range(C):
        # the captured (distorted) image of a round blob: each stored pixel sees the undistorted point it maps to
        und = undistort_points(pix[:, 0], Kcv[c], D[c]).reshape(size, size, 2) + 0.5  # splatrig convention
        uv = project(K[c], R[c], T[c], X)[0]
        g = np.exp(-((und[..., 0] - uv[0]) ** 2 + (und[..., 1] - uv[1]) ** 2) / (2 * 1.6**2))
        imgs.append(np.repeat(np.round(255 * g).astype(np.uint8)[..., None], 3, -1))
    w.write_frame(
        0,
        np.stack(imgs),
        np.ones((C, size, size), np.uint8),
        {"poses": np.zeros(72), "Rh": np.zeros(3), "Th": np.zeros(3)},
        X,
    )
    w.finish()
    ds = ZjuMocapDataset(str(tmp_path), protocol=None, mask_background=False)
    np.testing.assert_allclose(ds.cameras.K.double().numpy(), K, rtol=1e-6)  # K kept (in our pixel convention)
    for c in range(C):
        b = ds[c]
        uv = project(K[c], R[c], T[c], X)[0]  # undistorted pinhole projection
        found = centroid(b.image[0, ..., 0].double().numpy())
        assert np.abs(found - uv).max() < 0.1, (found, uv)
        stored = ZjuSequence(tmp_path).image(0, c)
        ref = cv2.undistort(stored, Kcv[c], D[c])
        assert np.abs(ref.astype(int) - (b.image[0].numpy() * 255).round().astype(int)).max() <= 1
        assert np.abs(centroid(stored[..., 0]) - uv).max() > 0.2  # the distortion was real (2x the tolerance)


# ------------------------------------------------------------------------------------------------ protocols
@pytest.fixture(scope="module")
def core313(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("zju") / "CoreView_313"
    write_core313_by_hand(root, C=21, F=64, size=8)
    return root


def test_aninerf_protocol_on_313(core313: Path) -> None:
    tr = ZjuMocapDataset(str(core313), split="train", protocol="aninerf_4view", boundary_px=1)
    assert tr.sequence == "313" and tr.train_views == [0, 6, 12, 18]
    assert tr.frame_ids == list(range(60)) and len(tr) == 240 and tr.num_frames_total == 64
    assert tr.sample(5) == (1, 6)  # frames outer, views inner
    nv = ZjuMocapDataset(str(core313), split="novel_view", protocol="aninerf_4view")
    assert nv.views == [v for v in range(21) if v not in (0, 6, 12, 18)] and nv.frame_ids == [0, 30]
    npose = ZjuMocapDataset(str(core313), split="novel_pose", protocol="aninerf_4view")
    assert npose.frame_ids == [60] and npose.views == nv.views  # frames 60.. clipped to the 64 present
    b = tr[1]
    assert int(b.frame[0]) == 0 and int(b.view[0]) == 6
    assert b.pose.shape == (1, 24, 3) and tr.poses().shape == (64, 24, 3) and tr.roots().shape == (64, 4, 4)
    assert tr.body_name == "smpl"  # no 'body' key in the public params


def test_dense_and_explicit_protocols(core313: Path) -> None:
    d = ZjuMocapDataset(str(core313), protocol="dense")
    assert d.test_views == [3, 9, 15] and len(d.train_views) == 18
    e = ZjuMocapDataset(
        str(core313),
        split="novel_pose",
        protocol="aninerf_4view",
        train_views=[1, 2],
        novel_pose_frames=[40, 64, 4],
        eval_frame_step=1,
    )
    assert e.frame_ids == list(range(40, 64, 4)) and 1 not in e.views and 0 in e.views
    with pytest.raises(ValueError, match="outside 0..63"):
        ZjuMocapDataset(str(core313), protocol=None, train_frames=[70])
    with pytest.raises(ValueError, match="unknown protocol 'aninerf'"):
        ZjuMocapDataset(str(core313), protocol="aninerf")


def test_protocol_needs_frames_for_unknown_sequence(tmp_path: Path) -> None:
    write_toy_sequence(tmp_path / "studio", C=4, F=3, size=16)
    with pytest.raises(ValueError, match="train_frames=\\[start, end, step\\]"):
        ZjuMocapDataset(str(tmp_path / "studio"), protocol="aninerf_4view")
    ds = ZjuMocapDataset(
        str(tmp_path / "studio"),
        split="novel_pose",
        protocol=None,
        train_frames=[0, 2],
        novel_pose_frames=[2, None],
        test_views=[3],
    )
    assert ds.frame_ids == [2] and ds.views == [3]


def test_h36m_layout(tmp_path: Path) -> None:
    """H36M/CMU preparations: 4 cameras named by serial under images/, masks by images -> mask; S9 -> views 0,1,2|3."""
    root = tmp_path / "S9" / "Posing"
    K, R, T = ring_cameras(4, size=8)
    serials = ["54138969", "55011271", "58860488", "60457274"]
    ims = [{"ims": [f"images/{s}/{f:06d}.jpg" for s in serials]} for f in range(3)]
    for row in ims:
        for rel in row["ims"]:
            for sub, val in ((rel, 90), (rel.replace("images", "mask").replace(".jpg", ".png"), 1)):
                (root / sub).parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(root / sub), np.full((8, 8), val, np.uint8))
    np.save(
        root / "annots.npy",
        {"cams": {"K": list(K), "D": [np.zeros((5, 1))] * 4, "R": list(R), "T": list(T[..., None] * 1000)}, "ims": ims},
        allow_pickle=True,
    )
    (root / "new_params").mkdir()
    for f in range(3):
        np.save(
            root / "new_params" / f"{f}.npy",
            {"poses": np.zeros((1, 72)), "Rh": np.zeros((1, 3)), "Th": np.zeros((1, 3)), "shapes": np.zeros((1, 10))},
        )
    ds = ZjuMocapDataset(str(root), split="novel_view", protocol="aninerf_4view", train_frames=[0, 3])
    assert ds.sequence == "S9" and ds.views == [3] and ds.train_views == [0, 1, 2]
    b = ds[0]
    assert b.mask.min() == 1 and abs(float(b.image.mean()) - 90 / 255) < 0.02
    # no vertices/: bounds from Th grown by 1.2 m (+ margin)
    torch.testing.assert_close(ds.bounds, torch.tensor([[-1.3] * 3, [1.3] * 3]))


# ------------------------------------------------------------------------------------------------ caches
def test_boundary_computed_once_memory_and_disk(tmp_path: Path) -> None:
    write_toy_sequence(tmp_path, C=2, F=2, size=32)
    ds = ZjuMocapDataset(str(tmp_path), protocol=None, boundary_px=3, boundary_cache="disk", cache_mb=0)
    first = [ds[i].boundary for i in range(len(ds))]
    again = [ds[i].boundary for i in range(len(ds))]
    assert ds.boundary_computations == len(ds) == 4
    for a, b in zip(first, again, strict=True):
        assert torch.equal(a, b)
    f, v = ds.sample(3)
    ref = boundary_mask(ZjuSequence(tmp_path).mask(f, v), 3)
    np.testing.assert_array_equal(first[3][0].numpy(), ref)
    assert len(list((tmp_path / ".splatrig_cache").rglob("*.npy"))) == 4
    ds2 = ZjuMocapDataset(str(tmp_path), protocol=None, boundary_px=3, boundary_cache="disk")
    assert torch.equal(ds2[3].boundary, first[3]) and ds2.boundary_computations == 0
    other = ZjuMocapDataset(
        str(tmp_path), protocol=None, boundary_px=1, boundary_cache="disk", cache_dir=str(tmp_path / "c")
    )
    assert not torch.equal(other[3].boundary, first[3]) and other.boundary_computations == 1


@pytest.mark.parametrize(("size", "downscale", "expected"), [(64, 1, 1), (256, 1, 3), (512, 1, 5), (512, 2, 3)])
def test_boundary_half_width_scales_with_the_image_side(tmp_path: Path, size: int, downscale: int, expected: int):
    """boundary_px=5 at boundary_ref_side=512: n = max(1, round(5 * side / 512)) of the output image (after the
    downscale), and the band is exactly `boundary_mask` at that n."""
    write_toy_sequence(tmp_path, C=2, F=1, size=size)
    ds = ZjuMocapDataset(
        str(tmp_path), protocol=None, boundary_px=5, boundary_ref_side=512, downscale=downscale, cache_mb=0
    )
    side = min(ds.width, ds.height)
    assert ds.boundary_px == expected == max(1, int(5 * side / 512 + 0.5))
    f, v = ds.sample(1)
    np.testing.assert_array_equal(ds[1].boundary[0].numpy(), boundary_mask(ds.load_uint8(f, v)[1] >= 128, expected))
    assert ZjuMocapDataset(str(tmp_path), protocol=None, boundary_px=5, cache_mb=0).boundary_px == 5  # unscaled


def test_lazy_uint8_cache_budget(tmp_path: Path) -> None:
    write_toy_sequence(tmp_path, C=3, F=3, size=32)
    one = 32 * 32 * 4  # image + mask, uint8
    ds = ZjuMocapDataset(str(tmp_path), protocol=None, cache_mb=2.5 * one / 2**20)
    for i in range(len(ds)):
        ds[i]
    assert len(ds._lru.items) == 2 and ds._lru.bytes <= 2.5 * one
    assert all(a.dtype == np.uint8 for v in ds._lru.items.values() for a in v)
    none = ZjuMocapDataset(str(tmp_path), protocol=None, cache_mb=0)
    none[0]
    assert len(none._lru.items) == 0


def test_background_and_registry(tmp_path: Path) -> None:
    write_toy_sequence(tmp_path, C=2, F=1, size=32)
    from framework.plugins import load_plugins
    from framework.registry import DATASETS

    load_plugins()
    white = DATASETS.build("zju_mocap", root=str(tmp_path), protocol=None, white_background=True)
    b = white[0]
    outside = b.mask[0] == 0
    assert outside.any() and torch.all(b.image[0][outside] == 1.0)
    black = ZjuMocapDataset(str(tmp_path), protocol=None)[0]
    assert torch.all(black.image[0][outside] == 0.0)
    assert torch.isfinite(black.image).all() and black.boundary.shape == black.mask.shape


# ------------------------------------------------------------------------------------------------ bad input
def test_bad_missing_annots(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"annots\.npy is missing.*expected annots\.npy") as e:
        ZjuMocapDataset(str(tmp_path / "nowhere"))
    assert "does not exist" in str(e.value)


def test_bad_camera_count(tmp_path: Path) -> None:
    write_toy_sequence(tmp_path, C=3, F=2, size=16)
    annots = np.load(tmp_path / "annots.npy", allow_pickle=True).item()
    for k in ("K", "D", "R", "T"):
        annots["cams"][k].append(annots["cams"][k][0])
    np.save(tmp_path / "annots.npy", annots)
    with pytest.raises(ZjuFormatError, match=r"frame 0 of 'ims' lists 3 images but 'cams' has 4 cameras"):
        ZjuMocapDataset(str(tmp_path), protocol=None)
    for k in ("K", "D", "R", "T"):
        annots["cams"][k].pop()
    np.save(tmp_path / "annots.npy", annots)
    import shutil

    shutil.rmtree(tmp_path / "Camera_B2")
    with pytest.raises(
        ZjuFormatError,
        match=r"'cams' has 3 cameras but 1 of their image folders are missing.*"
        r"Camera_B2.*found folders",
    ):
        ZjuMocapDataset(str(tmp_path), protocol=None)


def test_bad_mask_size(tmp_path: Path) -> None:
    write_toy_sequence(tmp_path, C=2, F=2, size=32)
    bad = tmp_path / "mask" / "Camera_B2" / "000001.png"
    cv2.imwrite(str(bad), np.ones((16, 20), np.uint8))
    with pytest.raises(ZjuFormatError, match=r"000001\.png \(frame 1, view 1\): mask is 20x16 .* is 32x32"):
        ZjuMocapDataset(str(tmp_path), protocol=None)  # found when the dataset is opened, not when frame 1 is read


def test_bad_nan_pose(tmp_path: Path) -> None:
    write_toy_sequence(tmp_path, C=2, F=3, size=16)
    p = np.load(tmp_path / "params" / "2.npy", allow_pickle=True).item()
    p["poses"][0, 16] = np.nan
    np.save(tmp_path / "params" / "2.npy", p)
    with pytest.raises(
        ZjuFormatError,
        match=r"params/2\.npy \(frame 2\): 'poses' has a non-finite value nan at "
        r"index 16 \(joint 5\); expected finite",
    ):
        ZjuMocapDataset(str(tmp_path), protocol=None)


def test_bad_body_joint_count(tmp_path: Path, body: ProceduralBody) -> None:
    write_toy_sequence(tmp_path, C=2, F=1, size=16, J=24, body="smpl")
    ds = ZjuMocapDataset(str(tmp_path), protocol=None)
    with pytest.raises(
        ZjuFormatError,
        match=r"params/0\.npy: stored poses have 24 joints \(72 values per frame\) "
        r"but body model 'procedural' has 17 joints.*body=smpl",
    ):
        check_body_compatible(ds, body)


def test_bad_missing_image(tmp_path: Path) -> None:
    write_toy_sequence(tmp_path, C=2, F=2, size=16)
    (tmp_path / "Camera_B1" / "000001.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"Camera_B1/000001\.png of frame 1, view 0 is missing"):
        ZjuMocapDataset(str(tmp_path), protocol=None)  # found when the dataset is opened
    ds = ZjuMocapDataset(str(tmp_path), protocol=None, train_frames=[0, 1])  # (start, end): frame 0 only
    with pytest.raises(FileNotFoundError, match=r"Camera_B1/000001\.png of frame 1, view 0 is missing"):
        ds.load_uint8(1, 0)


def test_bad_missing_params(tmp_path: Path) -> None:
    write_toy_sequence(tmp_path, C=2, F=2, size=16)
    (tmp_path / "params" / "1.npy").unlink()
    with pytest.raises(FileNotFoundError, match=r"params of frame 1 is missing: expected .*params/1\.npy"):
        ZjuMocapDataset(str(tmp_path), protocol=None)
    ok = ZjuMocapDataset(str(tmp_path), protocol=None, train_frames=[0, 1])  # frame 1 unused: rest pose, warning
    assert ok.poses()[1].abs().sum() == 0 and math.isfinite(float(ok.poses().sum()))


def test_preview_tool_writes_picture(tmp_path: Path, body: ProceduralBody) -> None:
    from tool_module import load_tool

    write_body_sequence(tmp_path / "seq", body, C=4, F=1, size=96)
    mod = load_tool("preview_sequence")
    out = tmp_path / "prev.png"
    assert mod.main(["--root", str(tmp_path / "seq"), "--frame", "0", "--out", str(out)]) == 0
    img = cv2.imread(str(out))
    assert img.shape == (768, 768, 3) and img.std() > 10
    shares = mod.preview(str(tmp_path / "seq"), 0, [0, 1, 2], str(out), crop=False)
    assert len(shares) == 3 and min(shares) >= 0.99

"""The ZJU-MoCap layout: writer -> reader round trips, the 313/315 naming written by hand, mask conventions, and the
boundary mask against a brute-force distance computation."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from framework.data.boundary import boundary_mask, boundary_mask_bruteforce
from framework.data.zju.layout import ZjuFormatError, frame_number_from_path, image_relpath, zju_camera_names
from framework.data.zju.reader import ZjuSequence
from framework.data.zju.writer import ZjuWriter


# ------------------------------------------------------------------------------------------------ synthetic rigs
def ring_cameras(C: int, radius: float = 3.0, height: float = 0.3, size: int = 64, f: float = 90.0, seed: int = 0):
    """A ring of OpenCV cameras around the origin (world z up), K in splatrig's pixel convention (centres at +0.5).
    Principal points are off-centre by sub-pixel amounts so that half-pixel mistakes show."""
    rng = np.random.default_rng(seed)
    K = np.zeros((C, 3, 3))
    R = np.zeros((C, 3, 3))
    T = np.zeros((C, 3))
    for c in range(C):
        a = 2 * math.pi * c / C
        eye = np.array([radius * math.cos(a), radius * math.sin(a), height])
        z = -eye / np.linalg.norm(eye)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R[c] = np.stack([x, y, z])
        T[c] = -R[c] @ eye
        K[c] = [
            [f * (1 + 0.05 * rng.random()), 0, size / 2 + rng.uniform(-3, 3)],
            [0, f * (1 + 0.05 * rng.random()), size / 2 + rng.uniform(-3, 3)],
            [0, 0, 1],
        ]
    return K, R, T


def project(K: np.ndarray, R: np.ndarray, T: np.ndarray, X: np.ndarray) -> np.ndarray:
    """[N, 3] world -> [N, 2] pixel coordinates in K's convention (float64 reference)."""
    p = X @ R.T + T
    uv = p @ K.T
    return uv[:, :2] / uv[:, 2:3]


def blob_image(uv: np.ndarray, size: int, sigma: float = 1.5) -> np.ndarray:
    """uint8 [H, W, 3]: one Gaussian blob centred at continuous `uv` (pixel centres at j + 0.5)."""
    jj, ii = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
    g = np.exp(-((jj - uv[0]) ** 2 + (ii - uv[1]) ** 2) / (2 * sigma**2))
    img = np.round(255 * g).astype(np.uint8)
    return np.stack([img, img // 2, 255 - img], -1)


def centroid(channel: np.ndarray) -> np.ndarray:
    """Intensity centroid in pixel-centre (+0.5) coordinates."""
    w = channel.astype(np.float64)
    jj, ii = np.meshgrid(np.arange(w.shape[1]) + 0.5, np.arange(w.shape[0]) + 0.5)
    return np.array([(w * jj).sum() / w.sum(), (w * ii).sum() / w.sum()])


def write_toy_sequence(
    root: Path,
    C: int = 4,
    F: int = 3,
    size: int = 64,
    style: str = "zju",
    image_ext: str = ".png",
    J: int = 24,
    seed: int = 0,
    body: str | None = "smpl",
) -> dict:
    """A tiny sequence: per frame one 3D marker drawn as a blob in every view, a disk mask around it, random params
    and a vertex cloud around the marker. Returns the ground truth used to write it."""
    rng = np.random.default_rng(seed)
    K, R, T = ring_cameras(C, size=size, seed=seed)
    w = ZjuWriter(root, zju_camera_names(C, style), style=style, image_ext=image_ext)
    w.write_cameras(K, None, R, T)
    markers = rng.uniform(-0.25, 0.25, (F, 3))
    params = []
    for f in range(F):
        uv = np.stack([project(K[c], R[c], T[c], markers[f : f + 1])[0] for c in range(C)])  # [C, 2]
        images = np.stack([blob_image(uv[c], size) for c in range(C)])
        masks = np.zeros((C, size, size), np.uint8)
        for c in range(C):
            cv2.circle(masks[c], (int(uv[c, 0]), int(uv[c, 1])), 6, 1, -1)
        p = {
            "poses": rng.normal(0, 0.3, (1, J * 3)),
            "Rh": rng.normal(0, 0.5, (1, 3)),
            "Th": markers[f][None],
            "shapes": rng.normal(0, 1, (1, 10)),
        }
        if body is not None:
            p["body"] = body
        params.append(p)
        verts = markers[f] + rng.normal(0, 0.02, (30, 3))
        w.write_frame(f, images, masks, p, verts)
    w.finish()
    return {"K": K, "R": R, "T": T, "markers": markers, "params": params, "size": size, "C": C, "F": F}


# ------------------------------------------------------------------------------------------------ writer/reader
def test_round_trip_values_and_files(tmp_path: Path) -> None:
    gt = write_toy_sequence(tmp_path, C=3, F=2)
    annots = np.load(tmp_path / "annots.npy", allow_pickle=True).item()
    # the public shapes: K (3,3), D (5,1), R (3,3), T (3,1) in millimetres; ims per frame per camera
    assert np.asarray(annots["cams"]["T"][1]).shape == (3, 1)
    assert np.asarray(annots["cams"]["D"][0]).shape == (5, 1)
    np.testing.assert_allclose(np.asarray(annots["cams"]["T"][1]).ravel(), gt["T"][1] * 1000)
    assert annots["ims"][1]["ims"] == ["Camera_B1/000001.png", "Camera_B2/000001.png", "Camera_B3/000001.png"]
    # K on disk is OpenCV's convention: half a pixel less than ours
    np.testing.assert_allclose(np.asarray(annots["cams"]["K"][2])[:2, 2], gt["K"][2][:2, 2] - 0.5)
    seq = ZjuSequence(tmp_path)
    assert seq.num_frames == 2 and seq.num_views == 3 and not seq.one_based
    np.testing.assert_allclose(seq.cameras.K_splatrig(), gt["K"])
    np.testing.assert_allclose(seq.cameras.world_to_cam()[:, :3, 3], gt["T"])
    p = seq.params(1)
    assert p["poses"].shape == (1, 72) and p["Rh"].shape == (1, 3) and p["shapes"].shape == (1, 10)
    assert p["body"] == "smpl"
    np.testing.assert_allclose(p["poses"], gt["params"][1]["poses"].astype(np.float32))
    assert seq.vertices(0).shape == (30, 3) and seq.vertices(0).dtype == np.float32
    assert seq.mask(0, 0).max() == 1 and seq.mask(0, 0).dtype == np.uint8
    assert seq.image(1, 2).shape == (64, 64, 3)


def test_writer_reprojection_png(tmp_path: Path) -> None:
    """Markers drawn where the written cameras put them are found where the reader's cameras project them."""
    gt = write_toy_sequence(tmp_path, C=4, F=3)
    seq = ZjuSequence(tmp_path)
    K, w2c = seq.cameras.K_splatrig(), seq.cameras.world_to_cam()
    for f in range(3):
        for c in range(4):
            uv = project(K[c], w2c[c, :3, :3], w2c[c, :3, 3], gt["markers"][f : f + 1])[0]
            found = centroid(seq.image(f, c)[..., 0])
            assert np.abs(found - uv).max() < 0.02, (f, c, found, uv)


def test_writer_parallel_finish(tmp_path: Path) -> None:
    """Frames written by separate writer instances; a third one (cameras from the partial file) finishes."""
    K, R, T = ring_cameras(2, size=16)
    names = zju_camera_names(2)
    a = ZjuWriter(tmp_path, names)
    a.write_cameras(K, None, R, T)
    assert not (tmp_path / "annots.npy").exists()
    with pytest.raises(FileNotFoundError, match="annots.npy is missing.*finish"):
        ZjuSequence(tmp_path)
    img = np.zeros((2, 16, 16, 3), np.uint8)
    msk = np.ones((2, 16, 16), np.uint8)
    par = {"poses": np.zeros(72), "Rh": np.zeros(3), "Th": np.zeros(3)}
    a.write_frame(1, img, msk, par, np.zeros((4, 3)))
    ZjuWriter(tmp_path, names).write_frame(0, img, msk, par, np.zeros((4, 3)))
    with pytest.raises(FileNotFoundError, match="never written"):
        ZjuWriter(tmp_path, names).finish(3)
    ZjuWriter(tmp_path, names).finish(2)
    assert ZjuSequence(tmp_path).num_frames == 2


def test_core313_naming_helpers() -> None:
    rel = image_relpath("Camera (3)", 543, "core313")
    assert rel.startswith("Camera (3)/CoreView_313_Camera_(3)_0544_2019-08-23_16-")
    # Neural Body / Animatable NeRF parse the frame as basename.split('_')[4]; it must agree with ours
    assert int(Path(rel).name.split("_")[4]) == 544 == frame_number_from_path(rel)
    assert frame_number_from_path("Camera (5)/CoreView_313_Camera_(5)_0001_2019-08-23_16-08-50.592.jpg") == 1
    assert frame_number_from_path("Camera_B16/000180.jpg") == 180
    assert frame_number_from_path("images/54138969/000005.jpg") == 5


def write_core313_by_hand(root: Path, C: int = 21, F: int = 64, size: int = 8, seed: int = 1) -> dict:
    """A 313-style sequence written without ZjuWriter, as the public download is: 'Camera (k)' folders, timestamped
    names, 1-based params/vertices numbering, CIHP part-label masks (RGB PNG), D as (5, 1), T as (3, 1) in mm."""
    rng = np.random.default_rng(seed)
    K, R, T = ring_cameras(C, size=size, f=10.0, seed=seed)
    Kcv = K.copy()
    Kcv[:, :2, 2] -= 0.5
    cams = {"K": list(Kcv), "D": [np.zeros((5, 1)) for _ in range(C)], "R": list(R), "T": list(T[..., None] * 1000)}
    ims = []
    for f in range(F):
        row = []
        for c in range(C):
            stamp = f"2019-08-23_16-08-{50 + f * 0.033:06.3f}"
            rel = f"Camera ({c + 1})/CoreView_313_Camera_({c + 1})_{f + 1:04d}_{stamp}.jpg"
            row.append(rel)
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(root / rel), np.full((size, size, 3), 40 + c, np.uint8))
            mrel = root / "mask_cihp" / (rel[:-4] + ".png")
            mrel.parent.mkdir(parents=True, exist_ok=True)
            labels = np.zeros((size, size, 3), np.uint8)
            labels[2:6, 3:5] = rng.integers(1, 20)  # a CIHP part label, not 1 or 255
            cv2.imwrite(str(mrel), labels)
        ims.append({"ims": row, "kpts2d": np.zeros((C, 25, 3))})
    np.save(root / "annots.npy", {"cams": cams, "ims": ims})
    (root / "params").mkdir()
    (root / "vertices").mkdir()
    poses = rng.normal(0, 0.2, (F, 72))
    for f in range(F):
        np.save(
            root / "params" / f"{f + 1}.npy",
            {
                "poses": poses[f][None],
                "Rh": rng.normal(0, 0.1, (1, 3)),
                "Th": rng.normal(0, 0.1, (1, 3)),
                "shapes": np.zeros((1, 10)),
            },
        )
        np.save(root / "vertices" / f"{f + 1}.npy", rng.normal(0, 0.3, (50, 3)).astype(np.float32))
    return {"K": K, "poses": poses}


def test_read_core313_by_hand(tmp_path: Path) -> None:
    root = tmp_path / "CoreView_313"
    gt = write_core313_by_hand(root, C=5, F=4)
    seq = ZjuSequence(root)
    assert seq.one_based and seq.file_numbers == [1, 2, 3, 4]
    assert seq.camera_dirs[:2] == ["Camera (1)", "Camera (2)"]
    assert seq.params_path(0).name == "1.npy"  # frame 0 is file 1
    np.testing.assert_allclose(seq.params(3)["poses"].ravel(), gt["poses"][3])
    np.testing.assert_allclose(seq.cameras.K_splatrig(), gt["K"])
    m = seq.mask(2, 1)
    assert m.sum() == 8 and set(np.unique(m)) == {0, 1}  # part labels read as foreground
    assert seq.available_mask_dirs() == ["mask_cihp"]
    assert seq.image(0, 4)[0, 0, 0] in range(42, 48)  # camera 5's grey (jpeg)


def test_mask_search_order_and_images_to_mask(tmp_path: Path) -> None:
    """EasyMocap-style 'images/<cam>/...' paths with masks under 'mask/<cam>/...' (Animatable NeRF's last fallback)."""
    K, R, T = ring_cameras(2, size=8)
    ims = [{"ims": [f"images/{c}/{f:06d}.jpg" for c in ("cam_a", "cam_b")]} for f in range(2)]
    for row in ims:
        for rel in row["ims"]:
            (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(tmp_path / rel), np.zeros((8, 8, 3), np.uint8))
            mp = tmp_path / rel.replace("images", "mask").replace(".jpg", ".png")
            mp.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(mp), np.full((8, 8), 255, np.uint8))
    np.save(
        tmp_path / "annots.npy",
        {"cams": {"K": list(K), "D": [np.zeros((5, 1))] * 2, "R": list(R), "T": list(T[..., None] * 1000)}, "ims": ims},
    )
    seq = ZjuSequence(tmp_path)
    assert seq.camera_dirs == ["images/cam_a", "images/cam_b"]
    assert seq.mask_path(1, 1).relative_to(tmp_path).as_posix() == "mask/cam_b/000001.png"
    assert seq.mask(1, 1).all()
    # the explicit mask/ folder mirroring the image path wins over the replace() fallback
    explicit = tmp_path / "mask" / "images" / "cam_b" / "000001.png"
    explicit.parent.mkdir(parents=True)
    cv2.imwrite(str(explicit), np.zeros((8, 8), np.uint8))
    assert seq.mask_path(1, 1) == explicit and seq.mask(1, 1).sum() == 0


def test_annots_errors(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"annots\.npy is missing"):
        ZjuSequence(tmp_path)
    np.save(tmp_path / "annots.npy", {"cams": {"K": [np.eye(3)]}})
    with pytest.raises(ZjuFormatError, match="expected keys 'cams' and 'ims'"):
        ZjuSequence(tmp_path)


# ------------------------------------------------------------------------------------------------ boundary
@pytest.mark.parametrize("n", [0, 1, 2, 3, 5])
def test_boundary_matches_bruteforce(n: int) -> None:
    rng = np.random.default_rng(n)
    for t in range(12):
        H, W = rng.integers(1, 18, 2)
        if t % 3 == 0:
            m = np.zeros((H, W), np.uint8)
            m[H // 4 : 3 * H // 4 + 1, W // 5 : 4 * W // 5 + 1] = 1
        elif t % 3 == 1:
            m = (rng.random((H, W)) < 0.5).astype(np.uint8)
        else:
            jj, ii = np.meshgrid(np.arange(W), np.arange(H))
            m = ((jj - W / 2) ** 2 + (ii - H / 3) ** 2 < (min(H, W) / 3) ** 2).astype(np.uint8) * 200
        np.testing.assert_array_equal(boundary_mask(m, n), boundary_mask_bruteforce(m, n))


def test_boundary_band_width_and_extremes() -> None:
    m = np.zeros((40, 40), np.uint8)
    m[:, 20:] = 1  # a vertical edge between columns 19 and 20
    b = boundary_mask(m, 5)
    assert b.dtype == np.float32
    np.testing.assert_array_equal(np.where(b[10] == 0)[0], np.arange(15, 25))  # 5 px each side
    assert boundary_mask(np.zeros((7, 9)), 5).min() == 1  # no silhouette, no band (image borders don't count)
    assert boundary_mask(np.ones((7, 9)), 5).min() == 1
    assert boundary_mask(np.zeros((0, 0)), 5).shape == (0, 0)
    single = np.zeros((1, 1))
    assert boundary_mask(single, 3).tolist() == [[1.0]]


@pytest.mark.parametrize("ext", [".jpg", ".png"])
def test_truncated_images_are_refused(tmp_path: Path, ext: str):
    """OpenCV decodes a JPEG cut in half without an error (grey below the cut): the end marker check refuses it."""
    from framework.data.zju.layout import ZjuFormatError, check_complete, read_image

    path = tmp_path / f"img{ext}"
    cv2.imwrite(str(path), (np.random.default_rng(0).random((40, 30, 3)) * 255).astype(np.uint8))
    check_complete(path)  # complete: no error
    assert read_image(path).shape == (40, 30, 3)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ZjuFormatError, match="is truncated"):
        read_image(path)

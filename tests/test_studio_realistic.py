"""The realistic studio: each capture imperfection is present in the written data, at the requested size, while the
images stay those of the clean pose and the exact silhouette."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from scipy.ndimage import distance_transform_edt
from scipy.spatial.transform import Rotation

from framework.data.studio import StudioSettings, generate
from framework.data.zju.layout import load_pickled_dict, read_image, read_mask_file

REALISTIC = StudioSettings(
    resolution=64,
    num_views=4,
    num_frames=12,
    seed=0,
    body="procedural",
    supersample=1,
    pose_noise_deg=3.0,
    root_noise_m=0.01,
    mask_error_px=3.0,
    garment="skirt",
    subject_height_fraction=0.85,
)


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    return generate(REALISTIC, tmp_path_factory.mktemp("realistic") / "seq", workers=1, progress=False)


@pytest.fixture(scope="module")
def body():
    from framework import plugins
    from framework.registry import BODIES

    plugins.load_plugins()
    return BODIES.build("procedural")


def _params(root, sub: str, f: int) -> dict:
    return load_pickled_dict(root / sub / "params" / f"{f}.npy")


def test_default_settings_keep_their_cache_key():
    """Knobs at their defaults leave the key (and so every sequence rendered before they existed) unchanged."""
    assert StudioSettings().key() == "2e28c7017374"
    assert StudioSettings(resolution=128, num_views=12, num_frames=60, supersample=2).key() == "3847c481d447"
    assert REALISTIC.key() != dataclasses.replace(REALISTIC, garment="none").key()


def test_stored_poses_carry_the_requested_fitting_noise(seq):
    """params/ vs ground_truth/params: per-joint rotation error of 3 degrees RMS, root jitter of 1 cm RMS."""
    angles, shifts = [], []
    for f in range(REALISTIC.num_frames):
        fit, clean = _params(seq, "", f), _params(seq, "ground_truth", f)
        a = Rotation.from_rotvec(fit["poses"].reshape(-1, 3).astype(np.float64))
        b = Rotation.from_rotvec(clean["poses"].reshape(-1, 3).astype(np.float64))
        angles.append(np.rad2deg((a * b.inv()).magnitude()))
        shifts.append(np.linalg.norm(fit["Th"] - clean["Th"]))
        np.testing.assert_array_equal(fit["Rh"], clean["Rh"])
    rms_angle = float(np.sqrt(np.mean(np.concatenate(angles) ** 2)))  # 17 joints x 12 frames
    rms_shift = float(np.sqrt(np.mean(np.square(shifts))))  # 12 frames
    assert rms_angle == pytest.approx(3.0, rel=0.15)
    assert rms_shift == pytest.approx(0.01, rel=0.4)


def test_images_come_from_the_clean_pose_and_the_fit_from_the_noisy_one(seq, body, tmp_path):
    """The images are byte for byte those of the same studio without pose noise or mask errors; vertices/ is the
    body posed by the noisy params (what a fit gives), ground_truth/vertices by the clean ones."""
    exact = dataclasses.replace(REALISTIC, pose_noise_deg=0.0, root_noise_m=0.0, mask_error_px=0.0)
    other = generate(exact, tmp_path / "exact", workers=1, progress=False)
    for rel in ("Camera_B1/000000.jpg", "Camera_B3/000007.jpg", "mask/Camera_B2/000011.png"):
        assert (seq / rel).read_bytes() == (other / rel).read_bytes(), rel
    from framework.geometry import axis_angle_to_rotmat

    for sub in ("", "ground_truth"):
        p = _params(seq, sub, 5)
        local = body.posed_vertices(torch.as_tensor(p["poses"].reshape(1, -1, 3)).double())[0]
        R = axis_angle_to_rotmat(torch.as_tensor(p["Rh"].reshape(3)).double())
        world = local @ R.T + torch.as_tensor(p["Th"].reshape(3)).double()
        stored = torch.as_tensor(np.load(seq / sub / "vertices" / "5.npy"), dtype=torch.float64)
        torch.testing.assert_close(world, stored, atol=1e-4, rtol=0)


def test_parser_masks_err_in_a_band_of_the_requested_width(seq):
    """mask_cihp/ differs from the exact mask/ only within the requested 3 px of the silhouette (+ half a pixel:
    the silhouette lies between pixel centres), reaches across most of that band, and is read by default."""
    w = REALISTIC.mask_error_px
    reach, changed_share = [], []
    for f in (0, 6, 11):
        for v in range(REALISTIC.num_views):
            rel = f"Camera_B{v + 1}/{f:06d}.png"
            exact = read_mask_file(seq / "mask" / rel).astype(bool)
            parsed = read_mask_file(seq / "mask_cihp" / rel).astype(bool)
            # distance from each pixel centre to the nearest pixel centre of the other label, by an independent EDT
            dist = np.where(exact, distance_transform_edt(exact), distance_transform_edt(~exact))
            changed = exact != parsed
            assert changed.any()
            assert dist[changed].max() <= w + 0.5 + 1e-6
            reach.append(dist[changed].max())
            edge = dist == 1  # pixels touching the silhouette
            changed_share.append(changed[edge].mean())
    assert min(reach) >= 0.6 * w
    assert np.mean(changed_share) > 0.3
    from framework.data.zju.dataset import ZjuMocapDataset

    ds = ZjuMocapDataset(root=str(seq), split="train", protocol=None, train_frames=[0, 12, 1], novel_pose_frames=[11])
    assert ds.seq.mask_path(0, 0).parent.parent.name == "mask_cihp"


def test_skirt_moves_unlike_the_body_skinning(seq, body):
    """The skirt's vertices are rendered (they fall inside the exact silhouettes) and are far from where the body's
    skinning would put them: weights from the nearest body surface (the avatar's initialisation) posed by LBS."""
    from framework.data.raycast import Camera
    from framework.data.zju.reader import ZjuSequence
    from framework.rig.weight_field import surface_weights

    rest = np.load(seq / "ground_truth" / "garment_rest.npy").astype(np.float64)
    w = surface_weights(body.rest_vertices, body.faces, body.skin_weights, rest)  # [Vs, J]
    zs = ZjuSequence(seq)
    errors, inside = [], []
    for f in range(REALISTIC.num_frames):
        p = _params(seq, "ground_truth", f)
        G = body.bone_transforms(torch.as_tensor(p["poses"].reshape(1, -1, 3)))[0].double().numpy()  # [J, 4, 4]
        blended = np.einsum("vj,jab->vab", w, G)  # [Vs, 4, 4]
        local = np.einsum("vab,vb->va", blended[:, :3, :3], rest) + blended[:, :3, 3]
        R = Rotation.from_rotvec(p["Rh"].reshape(3)).as_matrix()
        skinned = local @ R.T + p["Th"].reshape(3)
        truth = np.load(seq / "ground_truth" / "garment" / f"{f}.npy").astype(np.float64)
        errors.append(np.linalg.norm(truth - skinned, axis=1))
        for v in range(REALISTIC.num_views):
            w2c = zs.cameras.world_to_cam()[v]
            cam = Camera(zs.cameras.K_splatrig()[v], w2c, REALISTIC.resolution, REALISTIC.resolution)
            xy, _ = cam.project(truth)
            padded = np.pad(zs.mask(f, v, "mask").astype(bool), 1)
            n = REALISTIC.resolution  # one pixel of slack: a vertex on the outline may fall just outside
            near = np.max([padded[a : a + n, b : b + n] for a in range(3) for b in range(3)], axis=0)
            j, i = np.floor(xy).astype(int).T
            inside.append(near[i.clip(0, n - 1), j.clip(0, n - 1)].mean())
    errors = np.concatenate(errors)
    assert float(np.mean(inside)) > 0.97
    assert errors.mean() > 0.02 and np.percentile(errors, 95) > 0.05
    assert np.load(seq / "vertices" / "0.npy").shape == body.rest_vertices.shape  # the fit is the body alone


def test_subject_fills_the_requested_share_of_the_image_height(seq):
    heights = []
    for f in range(0, REALISTIC.num_frames, 3):
        for v in range(REALISTIC.num_views):
            rows = np.flatnonzero(read_mask_file(seq / "mask" / f"Camera_B{v + 1}/{f:06d}.png").any(1))
            heights.append((rows[-1] - rows[0] + 1) / REALISTIC.resolution)
    assert np.median(heights) == pytest.approx(0.85, abs=0.07)
    meta = json.loads((seq / "studio.json").read_text())
    assert meta["imperfections"]["subject_height_fraction"] == 0.85 and meta["ground_truth"] == "ground_truth"
    image = read_image(seq / "Camera_B1" / "000000.jpg")
    assert image.shape == (64, 64, 3)


def test_the_reader_takes_the_true_poses_when_asked(seq):
    """params_dir / vertices_dir select ground_truth/ (what the images were rendered from) over the noisy stored fit;
    a folder that does not exist is refused in one sentence."""
    from framework.data.zju.dataset import ZjuMocapDataset
    from framework.data.zju.layout import ZjuMissingFileError

    kw = dict(root=str(seq), split="train", protocol=None, train_frames=[0, 12, 1], novel_pose_frames=[11])
    true = ZjuMocapDataset(**kw, params_dir="ground_truth/params", vertices_dir="ground_truth/vertices")
    stored = ZjuMocapDataset(**kw)
    for f in (0, 5):
        clean, noisy = _params(seq, "ground_truth", f), _params(seq, ".", f)
        np.testing.assert_array_equal(true.seq.params(f)["poses"].reshape(-1), clean["poses"].reshape(-1))
        np.testing.assert_array_equal(stored.seq.params(f)["poses"].reshape(-1), noisy["poses"].reshape(-1))
        assert not np.allclose(clean["poses"], noisy["poses"])
        np.testing.assert_array_equal(true.seq.vertices(f), np.load(seq / "ground_truth" / "vertices" / f"{f}.npy"))
    with pytest.raises(ZjuMissingFileError, match="params_dir=truth: .* is not a folder; use params_dir=auto"):
        ZjuMocapDataset(**kw, params_dir="truth")

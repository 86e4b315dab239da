"""The synthetic studio: deterministic, cached, readable by the zju_mocap loader, geometrically consistent, and with
pose-dependent appearance."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from framework.data import raycast
from framework.data.studio import StudioSettings, generate

SMALL = StudioSettings(resolution=64, num_views=4, num_frames=3, seed=0, body="procedural", supersample=1)


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    return generate(SMALL, tmp_path_factory.mktemp("studio") / "seq", workers=1, progress=False)


def test_deterministic_for_a_seed(seq, tmp_path):
    again = generate(SMALL, tmp_path / "again", workers=2, progress=False)  # also: two processes, same bytes
    other = generate(StudioSettings(**{**SMALL.__dict__, "seed": 1}), tmp_path / "other", workers=1, progress=False)
    for rel in ("Camera_B1/000000.jpg", "Camera_B4/000002.jpg", "mask/Camera_B2/000001.png", "vertices/2.npy"):
        assert (seq / rel).read_bytes() == (again / rel).read_bytes(), rel
    a = np.load(seq / "params/1.npy", allow_pickle=True).item()
    b = np.load(again / "params/1.npy", allow_pickle=True).item()
    assert np.array_equal(a["poses"], b["poses"]) and a["body"] == "procedural"
    assert (seq / "Camera_B1/000000.jpg").read_bytes() != (other / "Camera_B1/000000.jpg").read_bytes()


def test_second_run_reuses_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(tmp_path))
    s = StudioSettings(**{**SMALL.__dict__, "num_frames": 2, "num_views": 2})
    first = generate(s, workers=1, progress=False)
    n = raycast.render_call_count()
    assert str(first).startswith(str(tmp_path)) and (first / "annots.npy").is_file()
    second = generate(s, workers=1, progress=False)
    assert second == first and raycast.render_call_count() == n


def test_layout_read_by_zju_loader_and_vertices_project_into_masks(seq):
    """The loader's cameras put >= 99% of the stored posed vertices inside the masks, allowing the 1-pixel
    silhouette band (a vertex on the silhouette lies in a pixel whose centre ray may just miss: with the centre-ray
    masks ~6-12% of a coarse mesh's vertices sit there at any resolution). And exactly: rays through the pixel
    centres from the loader's K and world_to_cam hit the stored posed mesh exactly where the mask is set."""
    import trimesh

    from framework import plugins
    from framework.data.zju.dataset import ZjuMocapDataset
    from framework.registry import BODIES

    plugins.load_plugins()
    faces = BODIES.build("procedural").faces.numpy()
    meta = json.loads((seq / "studio.json").read_text())
    assert meta["novel_pose_frames"] and meta["train_frames"]
    assert set(meta["train_frames"]).isdisjoint(meta["novel_pose_frames"])
    ds = ZjuMocapDataset(
        root=str(seq),
        split="train",
        protocol=None,
        train_frames=meta["train_frames"],
        novel_pose_frames=meta["novel_pose_frames"],
    )
    assert ds.body_name == "procedural" and ds.cameras.num == 4
    assert ds[0].image.shape == (1, 64, 64, 3) and ds[0].pose.shape == (1, 17, 3)
    inside = strict = total = 0
    agree = []
    for f in range(SMALL.num_frames):
        verts = np.load(seq / f"vertices/{f}.npy").astype(np.float64)  # [V, 3]
        mesh = trimesh.Trimesh(verts, faces, process=False)
        for v in range(4):
            K = ds.cameras.K[v].double().numpy()
            w2c = ds.cameras.world_to_cam[v].double().numpy()
            cam = verts @ w2c[:3, :3].T + w2c[:3, 3]
            uv = (cam @ K.T)[:, :2] / cam[:, 2:]
            mask = ds.seq.mask(f, v).astype(bool)  # [H, W] as stored
            padded = np.pad(mask, 1)
            dilated = np.max([padded[a : a + 64, b : b + 64] for a in range(3) for b in range(3)], axis=0)
            j, i = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
            assert ((j >= 0) & (j < 64) & (i >= 0) & (i < 64)).all()
            inside += int(dilated[i, j].sum())
            strict += int(mask[i, j].sum())
            total += len(verts)
            gj, gi = np.meshgrid(np.arange(64) + 0.5, np.arange(64) + 0.5)
            pix = np.stack([gj.ravel(), gi.ravel(), np.ones(64 * 64)], 1)
            dirs = (np.linalg.inv(K) @ pix.T).T @ w2c[:3, :3]
            center = -w2c[:3, :3].T @ w2c[:3, 3]
            hit = mesh.ray.intersects_any(np.tile(center, (len(dirs), 1)), dirs).reshape(64, 64)
            agree.append((hit == mask).mean())
    assert inside / total >= 0.99, inside / total
    assert strict / total >= 0.8, strict / total
    assert min(agree) >= 0.995, agree


def test_loaded_pose_and_root_reproduce_the_stored_vertices(seq):
    """params (poses, Rh, Th) + the body's LBS give the stored world vertices: the poses really belong to the body."""
    from framework import plugins
    from framework.data.zju.dataset import ZjuMocapDataset
    from framework.registry import BODIES

    plugins.load_plugins()
    body = BODIES.build("procedural")
    meta = json.loads((seq / "studio.json").read_text())
    ds = ZjuMocapDataset(
        root=str(seq),
        split="novel_pose",
        protocol=None,
        train_frames=meta["train_frames"],
        novel_pose_frames=meta["novel_pose_frames"],
    )
    item = ds[0]
    f = int(item.frame[0])
    local = body.posed_vertices(item.pose.double())[0]  # [V, 3]
    world = local @ item.root[0, :3, :3].double().T + item.root[0, :3, 3].double()
    stored = torch.as_tensor(np.load(seq / f"vertices/{f}.npy"), dtype=torch.float64)
    assert torch.allclose(world, stored, atol=1e-4)


def test_pose_dependent_shading_same_canonical_point():
    """Same body, same torso geometry, same camera; only the left arm moves (forward and up). The torso pixels see the
    same canonical points (same face ids) yet their colours change: self-shadow and wrinkles depend on the pose."""
    from framework import plugins
    from framework.data import studio
    from framework.data.appearance import Appearance
    from framework.data.motions import FWD, UP, Rig
    from framework.registry import BODIES

    plugins.load_plugins()
    body = BODIES.build("procedural")
    rig = Rig.from_body(body)
    faces = body.faces.numpy().astype(np.int64)
    app = Appearance(body.rest_vertices.numpy(), faces, body.skin_weights.numpy(), rig)
    rest_pose = np.zeros((rig.num_joints, 3), np.float32)
    moved = rest_pose.copy()
    moved[rig.index["shoulder.L"]] = rig.swing("shoulder.L", FWD, 1.2) + rig.swing("shoulder.L", UP, 0.6)
    moved[rig.index["elbow.L"]] = rig.swing("elbow.L", UP, 1.3)
    # wrinkles: none at rest, present near the flexed elbow
    assert np.allclose(app.wrinkle_multiplier(rest_pose), 1.0)
    m = app.wrinkle_multiplier(moved)
    near_elbow = np.linalg.norm(app.rest - rig.rest_joints[rig.index["elbow.L"]], axis=1) < 0.05
    flexed = rig.rest_joints[[rig.index["elbow.L"], rig.index["shoulder.L"]]]
    far = np.linalg.norm(app.rest[:, None] - flexed[None], axis=-1).min(1) > 0.5  # beyond the broad fold shade
    assert m[near_elbow].min() < 0.75 and np.allclose(m[far], 1.0, atol=1e-3)

    cam = raycast.Camera(
        raycast.intrinsics(40, 96, 96), raycast.look_at(np.array([1.0, -3.0, 1.0]), np.zeros(3) + [0, 0, 0.3]), 96, 96
    )  # noqa: E501
    outs = []
    for pose in (rest_pose, moved):
        verts = body.posed_vertices(torch.as_tensor(pose)[None])[0].double().numpy()
        wr = app.wrinkle_multiplier(pose)

        def color(fid, bary, _p, wr=wr):
            tri = faces[fid]
            return (
                app.albedo(fid, np.einsum("nk,nkc->nc", bary, app.rest[tri]))
                * np.einsum("nk,nk->n", bary, wr[tri])[:, None]
            )  # noqa: E501

        outs.append(raycast.render(verts, faces, cam, color_fn=color, shading=studio.LIGHT))
    a, b = outs
    torso = np.isin(
        a.face_ids,
        np.flatnonzero(
            np.isin(body.skin_weights.argmax(1).numpy()[faces[:, 0]], [rig.index["chest"], rig.index["spine"]])
        ),
    )
    same = torso & (a.face_ids == b.face_ids)
    assert same.sum() > 100
    diff = np.abs(a.rgb.astype(int) - b.rgb.astype(int)).max(-1)
    assert (diff[same] > 10).sum() > 20, (diff[same] > 10).sum()  # the arm's shadow on the torso


def test_synthetic_studio_dataset_splits(seq):
    from plugins.dataset.synthetic_studio import SyntheticStudioDataset

    kw = dict(
        root=str(seq), resolution=64, num_views=4, num_frames=3, seed=0, body="procedural", supersample=1, workers=1
    )
    train = SyntheticStudioDataset(split="train", **kw)
    nv = SyntheticStudioDataset(split="novel_view", **kw)
    npose = SyntheticStudioDataset(split="novel_pose", **kw)
    meta = json.loads((seq / "studio.json").read_text())
    assert train.views == [0, 1, 3] and nv.views == [2] and npose.views == [2]
    assert train.frame_ids == meta["train_frames"] and npose.frame_ids == meta["novel_pose_frames"]
    assert nv.frame_ids == meta["train_frames"]
    assert train.body_name == "procedural" and train.poses().shape == (3, 17, 3)
    b = npose[0]
    assert b.image.shape == (1, 64, 64, 3) and b.mask.sum() > 20 and b.boundary.min() == 0
    with pytest.raises(FileExistsError, match="other settings"):
        SyntheticStudioDataset(split="train", **{**kw, "seed": 5})


def test_interrupted_generation_resumes_without_redoing_frames(tmp_path, monkeypatch):
    """Killed after two frames, the sequence is not readable as complete (no annots.npy); a rerun renders only the
    two missing frames and the result is byte for byte the uninterrupted one."""
    import framework.data.studio as studio
    from framework.data.zju.reader import ZjuSequence

    settings = StudioSettings(**{**SMALL.__dict__, "resolution": 24, "num_views": 2, "num_frames": 4})
    rendered: list[int] = []
    real = studio._render_frame

    def interrupted(f: int) -> int:
        if len(rendered) == 2:
            raise KeyboardInterrupt
        rendered.append(f)
        return real(f)

    monkeypatch.setattr(studio, "_render_frame", interrupted)
    with pytest.raises(KeyboardInterrupt):
        generate(settings, tmp_path / "resumed", workers=1, progress=False)
    with pytest.raises(FileNotFoundError, match="annots.npy is missing"):
        ZjuSequence(tmp_path / "resumed")
    monkeypatch.setattr(studio, "_render_frame", lambda f: (rendered.append(f), real(f))[1])
    resumed = generate(settings, tmp_path / "resumed", workers=1, progress=False)
    assert rendered == [0, 1, 2, 3]  # nothing rendered twice
    whole = generate(settings, tmp_path / "whole", workers=1, progress=False)

    def listing(root):
        return sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file() and p.name != "studio.json")

    files = listing(whole)
    assert files == listing(resumed)
    for rel in files:
        assert (whole / rel).read_bytes() == (resumed / rel).read_bytes(), rel
    assert not list(resumed.glob(".*")), "leftovers of the interrupted run"


def test_the_command_renders_the_sequence_training_reads(tmp_path, monkeypatch):
    """`python -m framework.data.studio data=...` renders the same sequence (same settings hash, same folder) that a
    training run with that data config builds its dataset from."""
    from hydra import compose, initialize_config_module
    from omegaconf import OmegaConf

    from framework.build import build_split
    from framework.data.studio import generate_from_config

    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(tmp_path))
    small = ["data.body=procedural", "data.resolution=24", "data.num_views=2", "data.num_frames=4", "data.workers=1"]
    with initialize_config_module(config_module="framework.conf", version_base="1.3"):
        cfg = compose(config_name="studio", overrides=small)
    root, _ = generate_from_config(OmegaConf.to_container(cfg.data, resolve=True))
    dataset = build_split(cfg.data, "train")
    assert Path(dataset.seq.root).resolve() == root.resolve()
    assert root.parent == tmp_path / "data" / "synthetic_studio"

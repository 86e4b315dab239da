"""The static_scene dataset: deterministic, cached, and its cameras agree with its images."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from framework.data import raycast
from framework.data.static_scene import StaticSceneSettings, build_scene, ensure_static_scene

SMALL = dict(resolution=48, num_train_views=5, num_test_views=2, supersample=1)


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache"


def _dataset(split: str, **kw):
    from plugins.dataset.static_scene import StaticSceneDataset

    return StaticSceneDataset(split=split, **{**SMALL, **kw})


def test_same_seed_same_images_different_seed_different(tmp_path):
    s = StaticSceneSettings(**SMALL, seed=3)
    a = ensure_static_scene(s, tmp_path / "a")
    b = ensure_static_scene(s, tmp_path / "b")
    c = ensure_static_scene(StaticSceneSettings(**SMALL, seed=4), tmp_path / "c")
    for name in ("images/000.png", "images/006.png", "masks/003.png", "cameras.json"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    assert (a / "images/000.png").read_bytes() != (c / "images/000.png").read_bytes()


def test_second_use_reuses_cache(cache):
    before = raycast.render_call_count()
    d1 = _dataset("train")
    rendered = raycast.render_call_count() - before
    assert rendered == SMALL["num_train_views"] + SMALL["num_test_views"]
    mtime = (d1.path / "images" / "000.png").stat().st_mtime_ns
    d2 = _dataset("novel_view")
    assert raycast.render_call_count() - before == rendered  # nothing rendered again
    assert d2.path == d1.path and str(d1.path).startswith(str(cache))
    assert (d2.path / "images" / "000.png").stat().st_mtime_ns == mtime
    # other settings get their own directory
    d3 = _dataset("train", seed=1)
    assert d3.path != d1.path


def test_train_and_test_views_disjoint_and_complete(cache):
    tr, te, npose = _dataset("train"), _dataset("novel_view"), _dataset("novel_pose")
    assert len(tr) == 5 and len(te) == 2
    assert set(tr.views).isdisjoint(te.views)
    assert sorted(tr.views + te.views) == list(range(7))
    assert npose.views == te.views
    assert tr.cameras.num == 7
    centers = tr.cameras.centers()
    # no two cameras coincide (held-out views are really new viewpoints)
    dist = torch.cdist(centers, centers) + torch.eye(7) * 1e3
    assert dist.min() > 0.3


def test_items_are_framebatches(cache):
    d = _dataset("train")
    b = d[1]
    assert b.image.shape == (1, 48, 48, 3) and b.image.dtype == torch.float32
    assert 0 <= b.image.min() and b.image.max() <= 1
    assert b.mask.shape == (1, 48, 48) and torch.equal(b.boundary, torch.ones_like(b.mask))
    assert b.pose is None and b.root is None and int(b.frame) == 0 and int(b.view) == d.views[1]
    assert d.body_name is None and d.bounds.shape == (2, 3) and d.initial_points() is None
    # background is black, the foreground is not
    assert b.image[0][b.mask[0] == 0].max() == 0
    assert b.image[0][b.mask[0] == 1].mean() > 0.1
    with pytest.raises(ValueError, match="unknown split"):
        _dataset("validation")


def test_cameras_match_images(cache):
    """Project visible face centroids with the dataset's (torch) cameras: the pixel there is foreground, and a ray
    through that pixel centre, traced by trimesh's public ray API, hits that very face."""
    import trimesh

    d = _dataset("train")
    scene = build_scene(0)
    mesh = trimesh.Trimesh(scene.vertices, scene.faces, process=False)
    rng = np.random.default_rng(0)
    for idx, v in enumerate(d.views[:3]):
        K = d.cameras.K[v].double().numpy()
        w2c = d.cameras.world_to_cam[v].double().numpy()
        cam = (w2c[:3, :3] @ scene.vertices.T).T + w2c[:3, 3]  # float64 reference projection
        # every foreground pixel sees the mesh and every vertex lies in front of the camera
        assert (cam[:, 2] > 0).all()
        faces = rng.choice(len(scene.faces), 400, replace=False)
        cen = scene.vertices[scene.faces[faces]].mean(1)  # [400, 3]
        pc = (w2c[:3, :3] @ cen.T).T + w2c[:3, 3]
        pix = (K @ pc.T).T
        xy = pix[:, :2] / pix[:, 2:]
        inside = (xy > 1).all(1) & (xy < 47).all(1)
        jj, ii = np.floor(xy[:, 0]).astype(int), np.floor(xy[:, 1]).astype(int)
        center = -w2c[:3, :3].T @ w2c[:3, 3]
        # visible centroids: a ray from the camera centre towards the centroid first hits that face
        to_c = cen - center
        hit = mesh.ray.intersects_first(np.tile(center, (len(cen), 1)), to_c / np.linalg.norm(to_c, axis=1)[:, None])
        visible = inside & (hit == faces)
        assert visible.sum() > 40
        mask = d[idx].mask[0].numpy()
        # a visible centroid lies on the foreground, up to the pixel-centre sampling of the silhouette (1 px)
        padded = np.pad(mask, 1)
        dilated = np.max([padded[a : a + 48, b : b + 48] for a in range(3) for b in range(3)], axis=0)
        assert dilated[ii[visible], jj[visible]].min() == 1
        assert mask[ii[visible], jj[visible]].mean() > 0.5
        # every pixel: does the ray through its centre (from the dataset's K and world_to_cam) hit the mesh?
        gj, gi = np.meshgrid(np.arange(48) + 0.5, np.arange(48) + 0.5)
        pc_pix = np.stack([gj.ravel(), gi.ravel(), np.ones(48 * 48)], 1)
        dirs = (np.linalg.inv(K) @ pc_pix.T).T @ w2c[:3, :3]
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        any_hit = mesh.ray.intersects_any(np.tile(center, (len(dirs), 1)), dirs).reshape(48, 48)
        assert (any_hit == (mask > 0.5)).mean() > 0.998

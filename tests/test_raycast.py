"""The ray-cast ground-truth renderer against float64 brute force and closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from framework.data import raycast


def _brute_force(vertices, faces, origins, dirs):
    """float64 Moller-Trumbore over every (ray, triangle) pair: face id, barycentrics, t."""
    v = vertices[faces]  # [F, 3, 3]
    e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]  # [F, 3]
    p = np.cross(dirs[:, None], e2[None])  # [R, F, 3]
    det = np.einsum("rfc,fc->rf", p, e1)
    inv = 1.0 / np.where(np.abs(det) < 1e-15, np.nan, det)
    s = origins[:, None] - v[None, :, 0]
    u = np.einsum("rfc,rfc->rf", s, p) * inv
    q = np.cross(s, e1[None])
    w = np.einsum("rc,rfc->rf", dirs, q) * inv
    t = np.einsum("fc,rfc->rf", e2, q) * inv
    ok = (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0)
    t = np.where(ok, t, np.inf)
    fid = np.argmin(t, axis=1)
    tmin = t[np.arange(len(t)), fid]
    hit = np.isfinite(tmin)
    uu, ww = u[np.arange(len(t)), fid], w[np.arange(len(t)), fid]
    bary = np.stack([1 - uu - ww, uu, ww], 1)
    # margin to the runner-up (ties at shared edges are ambiguous)
    t_sorted = np.sort(t, axis=1)
    with np.errstate(invalid="ignore"):
        margin = np.where(hit, t_sorted[:, 1] - t_sorted[:, 0], np.inf)
    return np.where(hit, fid, -1), bary, np.where(hit, tmin, 0.0), margin


def _random_scene(seed=0, n=60):
    rng = np.random.default_rng(seed)
    centers = rng.uniform(-0.8, 0.8, (n, 3))
    tris = centers[:, None] + rng.normal(0, 0.25, (n, 3, 3))
    return tris.reshape(-1, 3), np.arange(3 * n).reshape(n, 3)


def _camera(w=24, h=20, eye=(0.3, -3.0, 1.2)):
    return raycast.Camera(raycast.intrinsics(45.0, w, h), raycast.look_at(np.array(eye), np.zeros(3)), w, h)


def test_hits_match_float64_brute_force():
    vertices, faces = _random_scene()
    cam = _camera()
    res = raycast.render(vertices, faces, cam)
    # independent rays: pixel centres (j + 0.5, i + 0.5) unprojected with float64 matrices
    jj, ii = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    pix = np.stack([jj.ravel(), ii.ravel(), np.ones(jj.size)], 1)
    R = cam.world_to_cam[:3, :3]
    dirs = (np.linalg.inv(cam.K) @ pix.T).T @ R
    origins = np.tile(cam.center, (len(dirs), 1))
    fid, bary, t, margin = _brute_force(vertices, faces, origins, dirs)
    got = res.face_ids.ravel()
    clear = margin > 1e-4
    assert (got == fid)[clear].mean() == 1.0
    assert (got >= 0).sum() > 100 and (got < 0).sum() > 20  # both hits and misses are exercised
    hit = (fid >= 0) & clear
    # dirs have camera z = 1, so t is the camera depth
    np.testing.assert_allclose(res.depth.ravel()[hit], t[hit], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(res.bary.reshape(-1, 3)[hit], bary[hit], atol=2e-4)
    assert np.allclose(res.bary.reshape(-1, 3)[hit].sum(1), 1.0, atol=1e-5)
    assert (res.depth[res.face_ids < 0] == 0).all() and (res.rgb[res.face_ids < 0] == 0).all()


def test_pixel_centre_convention_and_projection():
    """A vertex projected with K and world_to_cam lands at (j + 0.5, i + 0.5) of the pixel whose ray hits near it."""
    vertices = np.array([[-0.5, 0.0, -0.5], [0.5, 0.0, -0.5], [0.0, 0.0, 0.5]])
    faces = np.array([[0, 1, 2]])
    cam = _camera(w=64, h=64, eye=(0.0, -3.0, 0.0))
    res = raycast.render(vertices, faces, cam)
    hit = np.argwhere(res.mask)
    pts = np.einsum("nk,kc->nc", res.bary[res.mask].astype(np.float64), vertices)
    xy, z = cam.project(pts)
    np.testing.assert_allclose(xy[:, 0], hit[:, 1] + 0.5, atol=1e-3)
    np.testing.assert_allclose(xy[:, 1], hit[:, 0] + 0.5, atol=1e-3)
    np.testing.assert_allclose(z, res.depth[res.mask], rtol=1e-5)
    # OpenCV: the apex (world +z) is at the top of the image (small row index)
    top, bottom = hit[:, 0].min(), hit[:, 0].max()
    assert (hit[:, 0] == top).sum() < (hit[:, 0] == bottom).sum() / 4


def test_texture_lookup_bilinear_and_orientation():
    tex = np.zeros((4, 4, 3), np.uint8)
    tex[0, :, 0] = 255  # top row red: v near 1
    tex[3, :, 2] = 255  # bottom row blue: v near 0
    c = raycast.sample_texture(tex, np.array([[0.5, 7 / 8], [0.5, 1 / 8], [0.5, 0.75]]))
    np.testing.assert_allclose(c[0], [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(c[1], [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(c[2], [0.5, 0, 0], atol=1e-6)  # halfway between texel rows 0 and 1


def test_uv_texture_render_matches_direct_lookup():
    vertices = np.array([[-1.0, 0.0, -1.0], [1.0, 0.0, -1.0], [1.0, 0.0, 1.0], [-1.0, 0.0, 1.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uvs = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    rng = np.random.default_rng(1)
    tex = rng.integers(0, 256, (8, 8, 3)).astype(np.uint8)
    cam = _camera(w=32, h=32, eye=(0.0, -3.0, 0.0))
    res = raycast.render(vertices, faces, cam, texture=tex, uvs=uvs, face_uvs=faces)
    m = res.mask
    pts = np.einsum("nk,nkc->nc", res.bary[m], vertices[faces[res.face_ids[m]]])
    uv = np.stack([(pts[:, 0] + 1) / 2, (pts[:, 2] + 1) / 2], 1)  # planar map of this quad
    expect = np.clip(np.round(raycast.sample_texture(tex, uv) * 255), 0, 255)
    assert np.abs(res.rgb[m].astype(int) - expect).max() <= 1


def test_lambert_closed_form_and_cast_shadow():
    # ground quad at z = 0, a small occluder quad at z = 0.5 above its centre; light straight down (from +z)
    ground = np.array([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], float)
    occ = np.array([[-0.3, -0.3, 0.5], [0.3, -0.3, 0.5], [0.3, 0.3, 0.5], [-0.3, 0.3, 0.5]])
    vertices = np.concatenate([ground, occ])
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    cam = raycast.Camera(
        raycast.intrinsics(50.0, 48, 48), raycast.look_at(np.array([0.0, -3.0, 4.0]), np.zeros(3)), 48, 48
    )
    light = (0.0, 0.0, 1.0)
    ambient, diffuse = 0.2, 0.6
    shaded = raycast.Shading(direction=light, ambient=ambient, diffuse=diffuse, shadows=True, smooth_normals=False)
    res = raycast.render(vertices, faces, cam, shading=shaded)
    fid = res.face_ids
    pts = np.zeros(fid.shape + (3,))
    m = fid >= 0
    pts[m] = np.einsum("nk,nkc->nc", res.bary[m], vertices[faces[fid[m]]])
    on_ground = (fid == 0) | (fid == 1)
    under = on_ground & (np.abs(pts[..., 0]) < 0.25) & (np.abs(pts[..., 1]) < 0.25)
    free = on_ground & ((np.abs(pts[..., 0]) > 0.35) | (np.abs(pts[..., 1]) > 0.35))
    assert under.sum() > 5 and free.sum() > 50
    assert (res.rgb[under] == round(255 * ambient)).all()  # shadowed: ambient only
    assert (res.rgb[free] == round(255 * (ambient + diffuse))).all()  # lit, n.l = 1
    occluder = (fid == 2) | (fid == 3)
    assert (res.rgb[occluder] == round(255 * (ambient + diffuse))).all()  # nothing above it
    # without shadow rays the ground under the occluder is lit
    res2 = raycast.render(vertices, faces, cam, shading=raycast.Shading(light, ambient, diffuse, smooth_normals=False))
    assert (res2.rgb[under] == round(255 * (ambient + diffuse))).all()


def test_supersampled_coverage_of_a_half_plane():
    # a quad covering x >= 0 of the view exactly through pixel boundaries: coverage is 0, 1 or 0.5 at the edge column
    w = h = 16
    K = np.array([[16.0, 0, 8.25], [0, 16.0, 8.0], [0, 0, 1]])  # principal point 0.25 px right of a pixel boundary
    cam = raycast.Camera(K, np.eye(4), w, h)
    vertices = np.array([[0.0, -5, 1], [5, -5, 1], [5, 5, 1], [0, 5, 1]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    res = raycast.render(vertices, faces, cam, vertex_colors=np.ones((4, 3)), supersample=4)
    # the edge x = 0 projects to image x = 8.25: column 8 has 3 of 4 sub-columns hit (offsets .125 .375 .625 .875)
    np.testing.assert_allclose(res.coverage[:, 8], 0.75)
    assert (res.coverage[:, :8] == 0).all() and (res.coverage[:, 9:] == 1).all()
    assert res.mask[:, 8].all() and not res.mask[:, 7].any()
    assert (res.rgb[:, 8] == round(0.75 * 255)).all()


def test_empty_mesh_and_bad_input():
    cam = _camera()
    res = raycast.render(np.zeros((0, 3)), np.zeros((0, 3), np.int64), cam, supersample=2)
    assert not res.mask.any() and (res.rgb == 0).all() and (res.face_ids == -1).all()
    with pytest.raises(ValueError, match="face indices"):
        raycast.RayCaster(np.zeros((3, 3)), np.array([[0, 1, 5]]))
    with pytest.raises(ValueError, match="NaN"):
        raycast.RayCaster(np.full((3, 3), np.nan), np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match="uvs"):
        raycast.render(np.eye(3), np.array([[0, 1, 2]]), cam, texture=np.zeros((2, 2, 3)))


def test_occlusion_segments():
    vertices = np.array([[-1.0, -1.0, 1.0], [1.0, -1.0, 1.0], [0.0, 1.0, 1.0]])
    rc = raycast.RayCaster(vertices, np.array([[0, 1, 2]]))
    o = np.zeros((3, 3))
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    assert rc.occluded(o, d, np.array([2.0, 0.5, 2.0])).tolist() == [True, False, False]

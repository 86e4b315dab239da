"""The interactive viewer: camera conversion, the session's switches, and the real page in a headless Chromium."""

from __future__ import annotations

import io
import os
import re

import numpy as np
import pytest
import torch
from trained_avatar import load_tiny

from framework.cameras import look_at
from framework.testing.browser import HeadlessChromium, find_chromium
from framework.testing.viewer import (
    CLOSE_NOTIFICATIONS,
    FRAMES_SERVED,
    PANEL_LEFT,
    SLIDER,
    running_viewer,
    settled_screenshot,
)
from framework.viewer.camera import render_size, viser_camera


@pytest.fixture(scope="module")
def tiny(tiny_avatar):
    return tiny_avatar


def test_viser_camera_is_the_look_at_camera():
    """viser reports R (camera-to-world, OpenCV axes) as a quaternion and the vertical field of view; converted, the
    camera equals our look-at camera and the target projects to the image centre at the expected focal length."""
    import viser.transforms as vtf

    eye, target = torch.tensor([1.5, -2.0, 1.2]), torch.tensor([0.1, 0.2, 0.9])
    w2c = look_at(eye, target, torch.tensor([0.0, 0.0, 1.0]))
    wxyz = vtf.SO3.from_matrix(w2c[:3, :3].T.double().numpy()).wxyz
    cam = viser_camera(wxyz, eye.numpy(), np.radians(50.0), 320, 200)
    assert torch.allclose(cam.world_to_cam[0], w2c, atol=1e-6)
    p = cam.K[0] @ (cam.world_to_cam[0, :3, :3] @ target + cam.world_to_cam[0, :3, 3])
    assert torch.allclose(p[:2] / p[2], torch.tensor([160.0, 100.0]), atol=1e-4)
    assert float(cam.K[0, 1, 1]) == pytest.approx(100.0 / np.tan(np.radians(25.0)), rel=1e-6)
    assert render_size(1.6, 320) == (320, 200) and render_size(0.5, 300) == (150, 300)


def test_session_switches_change_what_is_rendered(tiny, tmp_path, monkeypatch):
    from framework.animation.camera_paths import subject_view
    from framework.cameras import orbit_cameras
    from framework.viewer.session import ViewerSession

    ckpt, cache = tiny
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(cache))
    module, dm = load_tiny(ckpt)
    session = ViewerSession(module, dm)
    assert list(session.motions) == ["train", "novel_pose"]
    center, distance, fov = subject_view(module, dm)
    camera = orbit_cameras(center, distance, 0.0, 1, 48, 48, fov_deg=fov)

    def diff(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.abs(a.astype(int) - b.astype(int)).mean())

    base = session.render(camera)
    assert base.shape == (48, 48, 3) and base.max() > 0 and session.last.served == 1
    session.set_offset(session.joint_names.index("upperarm.L"), [0, 0, 60])
    assert diff(session.render(camera), base) > 0.2  # the left arm swings forward
    session.reset_offsets()
    assert diff(session.render(camera), base) == 0
    session.set_corrector(False)
    assert diff(session.render(camera), base) > 0.05  # F_a off: the average appearance
    session.set_corrector(True)
    assert diff(session.render(camera), base) == 0
    assert session.has_residual
    session.set_residual(False)
    assert diff(session.render(camera), base) > 0.05  # F_dw off: the grid's blend weights
    session.set_residual(True)
    assert diff(session.render(camera), base) == 0
    session.select("novel_pose", 0)
    assert session.current_pose()[2] == dm.split("novel_pose").frame_ids[0]
    poses = np.zeros((3, 17, 3), np.float32)
    poses[:, 5, 2] = [0.0, 0.5, 1.0]
    np.savez(tmp_path / "wave.npz", poses=poses)
    name = session.add_motion_file(str(tmp_path / "wave.npz"))
    session.select(name, 2)
    pose, root, frame_id = session.current_pose()
    assert torch.allclose(pose, torch.as_tensor(poses[2])) and root is None and frame_id == -1
    session.select(frame=99)  # clamped to the motion
    assert session.frame == 2
    if "jax" in session.available_backends():
        session.select("train", 0)
        session.set_backend("jax")
        assert diff(session.render(camera), base) < 1.0  # another backend, the same picture


def canvas_pixels(png: bytes, panel_left: int) -> np.ndarray:
    import imageio.v3 as iio

    return iio.imread(io.BytesIO(png))[:, :panel_left, :3].astype(int)


@pytest.mark.skipif(
    find_chromium() is None,
    reason="Chromium is not installed (Debian: apt-get install chromium); "
    "the viewer's browser test needs a real browser",
)
def test_viewer_page_in_a_real_browser_poses_the_avatar(tiny, tmp_path):
    """Start `python -m framework.view`, open it in headless Chromium, drag a joint slider with the mouse and check
    that the server renders and sends a different frame (the canvas pixels change)."""
    ckpt, cache = tiny
    env = dict(os.environ, SPLATRIG_CACHE_DIR=str(cache))
    with running_viewer(ckpt, "resolution=128", "device=cpu", env=env, cwd=tmp_path) as url:
        with HeadlessChromium(1000, 700, timeout=60) as browser:
            browser.goto(url)
            browser.wait_for(f"{FRAMES_SERVED} >= 1", timeout=90)
            assert re.search(r"\d+ Gaussians", browser.evaluate("document.body.innerText"))
            browser.evaluate(CLOSE_NOTIFICATIONS)
            panel_left = int(browser.evaluate(PANEL_LEFT)) - 40
            before = canvas_pixels(settled_screenshot(browser), panel_left)
            served = browser.evaluate(FRAMES_SERVED)
            left, right, x, y, value = browser.evaluate(SLIDER.format(label="rotate y (deg)"))
            assert value == 0
            browser.drag(x, y, left + 0.25 * (right - left), y)  # about -90 deg: the left arm turns up
            assert browser.evaluate(SLIDER.format(label="rotate y (deg)"))[4] < -45  # the page's slider moved
            browser.wait_for(f"{FRAMES_SERVED} > {served}", timeout=60)  # the server rendered the new pose
            after = canvas_pixels(settled_screenshot(browser), panel_left)  # and the browser drew it
    assert before.max() > 0
    changed = (np.abs(after - before).max(-1) > 16).mean()  # fraction of canvas pixels that changed visibly
    assert changed > 0.002, f"the frame shown did not change after moving the joint slider ({changed:.5f})"

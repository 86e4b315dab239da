"""The interactive viewer: camera conversion, the session's switches, and the real page in a headless Chromium."""

from __future__ import annotations

import io
import os
import re
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from trained_avatar import load_tiny, tiny_checkpoint

from framework.cameras import look_at
from framework.testing.browser import HeadlessChromium, find_chromium
from framework.viewer.camera import render_size, viser_camera


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return tiny_checkpoint(tmp_path_factory.mktemp("tiny_avatar"))


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


def test_session_switches_change_what_is_rendered(tiny, monkeypatch):
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
    if "jax" in session.available_backends():
        session.select("train", 0)
        session.set_backend("jax")
        assert diff(session.render(camera), base) < 1.0  # another backend, the same picture


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


SLIDER = """(() => {{
  const label = Array.from(document.querySelectorAll('label')).find(e => e.textContent === {label!r});
  const root = document.getElementById(label.htmlFor);
  const track = root.querySelector('.mantine-Slider-track').getBoundingClientRect();
  const thumb = root.querySelector('[role=slider]');
  const t = thumb.getBoundingClientRect();
  return [track.left, track.right, t.left + t.width / 2, t.top + t.height / 2, Number(thumb.getAttribute('aria-valuenow'))];
}})()"""  # noqa: E501
SERVED = "(document.body.innerText.match(/frames served: (\\d+)/) || [null, 0])[1] * 1"


def canvas_pixels(png: bytes, panel_left: int) -> np.ndarray:
    import imageio.v3 as iio

    return iio.imread(io.BytesIO(png))[:, :panel_left, :3].astype(int)


@pytest.mark.skipif(find_chromium() is None, reason="Chromium is not installed (Debian: apt-get install chromium); "
                                                     "the viewer's browser test needs a real browser")  # fmt: skip
def test_viewer_page_in_a_real_browser_poses_the_avatar(tiny, tmp_path):
    """Start `python -m framework.view`, open it in headless Chromium, drag a joint slider with the mouse and check
    that the server renders and sends a different frame (the canvas pixels change)."""
    ckpt, cache = tiny
    port = _free_port()
    env = dict(os.environ, SPLATRIG_CACHE_DIR=str(cache), PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "framework.view", f"ckpt={ckpt}", f"port={port}", "resolution=128", "device=cpu"]
    viewer = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path)
    try:
        deadline = time.monotonic() + 180
        for line in viewer.stdout:
            if f"viewer at http://127.0.0.1:{port}" in line:
                break
            assert time.monotonic() < deadline, "the viewer did not start in time"
        else:
            pytest.fail(f"the viewer exited early (code {viewer.wait()})")
        with HeadlessChromium(1000, 700, timeout=60) as browser:
            browser.goto(f"http://127.0.0.1:{port}")
            browser.wait_for(f"{SERVED} >= 1", timeout=90)
            assert re.search(r"\d+ Gaussians", browser.evaluate("document.body.innerText"))
            time.sleep(1.0)  # let the first frame reach the canvas
            panel_left = int(browser.evaluate("document.querySelector('label').getBoundingClientRect().left")) - 40
            before = canvas_pixels(browser.screenshot(), panel_left)
            served = browser.evaluate(SERVED)
            left, right, x, y, value = browser.evaluate(SLIDER.format(label="rotate z (deg)"))
            assert value == 0
            browser.drag(x, y, left + 0.85 * (right - left), y)
            assert browser.evaluate(SLIDER.format(label="rotate z (deg)"))[4] > 90  # the page's slider moved
            browser.wait_for(f"{SERVED} > {served}", timeout=60)  # the server rendered the new pose
            time.sleep(1.5)  # and the browser received and drew it
            after = canvas_pixels(browser.screenshot(), panel_left)
        assert before.max() > 0
        assert np.abs(after - before).mean() > 0.5, "the frame shown did not change after moving the joint slider"
    finally:
        viewer.terminate()
        try:
            viewer.wait(timeout=20)
        except subprocess.TimeoutExpired:
            viewer.kill()
            viewer.wait()

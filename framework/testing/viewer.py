"""`python -m framework.view` as a child process, for end-to-end tests and documentation screenshots."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

# JavaScript: the number of frames the viewer says it has served (its status line), 0 before the first
FRAMES_SERVED = "(document.body.innerText.match(/frames served: (\\d+)/) || [null, 0])[1] * 1"

# JavaScript: the render rate the status line reports (frames per second of the last render), 0 before the first
RENDER_FPS = "(document.body.innerText.match(/([0-9.]+) fps/) || [null, 0])[1] * 1"

# JavaScript: close viser's notifications (e.g. "Software WebGL rendering detected"), which cover the canvas
CLOSE_NOTIFICATIONS = "document.querySelectorAll('.mantine-Notification-closeButton').forEach(b => b.click())"

# JavaScript: x of the control panel's left edge (the leftmost visible widget label), in CSS pixels
PANEL_LEFT = (
    "Math.min(...Array.from(document.querySelectorAll('label')).map(l => l.getBoundingClientRect().left)"
    ".filter(x => x > 0))"
)

# JavaScript template: [track left, track right, thumb x, thumb y, value] of the viewer slider labelled {label!r}
SLIDER = """(() => {{
  const label = Array.from(document.querySelectorAll('label')).find(e => e.textContent === {label!r});
  const root = document.getElementById(label.htmlFor);
  const track = root.querySelector('.mantine-Slider-track').getBoundingClientRect();
  const thumb = root.querySelector('[role=slider]');
  const t = thumb.getBoundingClientRect();
  return [track.left, track.right, t.left + t.width / 2, t.top + t.height / 2,
          Number(thumb.getAttribute('aria-valuenow'))];
}})()"""


def settled_screenshot(browser, quiet: float = 2.0, timeout: float = 120.0) -> bytes:
    """A screenshot once the viewer has served no new frame for a while and two screenshots in a row agree: the last
    change has been rendered, sent and drawn. "A while" is `quiet` seconds, or three render times when the status
    line reports slower renders (a busy CPU can take seconds per frame, and a change made during a render is only
    rendered after it)."""
    deadline = time.monotonic() + timeout
    served, since = browser.evaluate(FRAMES_SERVED), time.monotonic()
    last = None
    while True:
        time.sleep(0.5)
        fps = browser.evaluate(RENDER_FPS)
        wait = max(quiet, 3.0 / fps if fps else quiet)
        now_served = browser.evaluate(FRAMES_SERVED)
        if now_served != served:
            served, since, last = now_served, time.monotonic(), None
            continue
        shot = browser.screenshot()
        if time.monotonic() - since >= wait and shot == last:
            return shot
        last = shot
        if time.monotonic() > deadline:
            raise TimeoutError("the viewer page did not settle")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def running_viewer(
    ckpt: str | Path,
    *overrides: str,
    env: dict[str, str] | None = None,
    cwd: str | Path | None = None,
    timeout: float = 180.0,
) -> Iterator[str]:
    """Start the viewer on a free localhost port, yield its URL once it serves, stop it afterwards."""
    port = free_port()
    cmd = [sys.executable, "-m", "framework.view", f"ckpt={ckpt}", f"port={port}", *overrides]
    proc = subprocess.Popen(
        cmd,
        env=dict(env or os.environ, PYTHONUNBUFFERED="1"),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=cwd,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + timeout
        seen: list[str] = []
        assert proc.stdout is not None
        for line in proc.stdout:
            seen.append(line)
            if f"viewer at {url}" in line:
                break
            if time.monotonic() > deadline:
                raise TimeoutError(f"the viewer did not start within {timeout:.0f} s:\n{''.join(seen[-20:])}")
        else:
            raise RuntimeError(f"the viewer exited with code {proc.wait()}:\n{''.join(seen[-20:])}")
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()

"""The viewer's web page (viser): widgets that drive a `ViewerSession`, and a loop that renders each browser's view.

Panels: Motion (which motion, frame slider, play), Pose (a joint and three rotation sliders on top of the motion,
reset), Model (the corrector F_a and weight residual F_dw switches, rasterizer backend, resolution) and a status line
(frames per second of the render, Gaussian count, image size, frames served). Rendering happens here on the server
with our rasterizers; the browser shows each frame as the scene's background image, so the page stays light and
every backend (CPU or GPU) can be compared in the same place.
"""

from __future__ import annotations

import math
import threading
import time
import traceback
import warnings

import numpy as np

from framework.errors import SplatrigError
from framework.viewer.camera import render_size, viser_camera
from framework.viewer.session import ViewerSession

POSE_AXES = ("x", "y", "z")


class ViewerApp:
    def __init__(
        self,
        session: ViewerSession,
        host: str = "127.0.0.1",
        port: int = 8080,
        max_side: int = 384,
        view: tuple[np.ndarray, float, float] | None = None,
    ) -> None:
        import viser

        self.session = session
        self.max_side = int(max_side)
        self.server = viser.ViserServer(host=host, port=port, label="splatrig", verbose=False)
        self.server.scene.set_up_direction("+z")
        self._dirty: set[int] = set()
        self._dirty_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._local = threading.local()  # .syncing: this thread is setting widgets itself (not a person)
        if view is not None:
            center, distance, fov_deg = view
            cam = self.server.initial_camera
            cam.look_at = tuple(float(x) for x in center)
            cam.position = tuple(float(x) for x in center + distance * np.array([0.35, -0.94, 0.1]))
            cam.up = (0.0, 0.0, 1.0)
            cam.fov = math.radians(fov_deg)
        self._build_gui()
        self.server.on_client_connect(self._on_connect)

    @property
    def port(self) -> int:
        return int(self.server.get_port())

    # ------------------------------------------------------------------------------------------------ widgets
    def _build_gui(self) -> None:
        gui, s = self.server.gui, self.session
        self.status = gui.add_markdown("starting ...")
        with gui.add_folder("Motion", visible=bool(s.motions)):
            names = list(s.motions) or ["(none)"]
            self.motion = gui.add_dropdown("motion", names, initial_value=s.motion_name or names[0])
            self.frame = gui.add_slider("frame", 0, max(s.num_frames - 1, 0), 1, 0)
            self.play = gui.add_checkbox("play", False)
            self.motion_file = gui.add_text("motion file", "")
            self.load = gui.add_button("load motion file")
        with gui.add_folder("Pose", visible=bool(s.joint_names)):
            joints = s.joint_names or ["(none)"]
            self.joint = gui.add_dropdown("joint", joints, initial_value=s.default_joint or joints[0])
            self.rotation = [gui.add_slider(f"rotate {a} (deg)", -180, 180, 1, 0) for a in POSE_AXES]
            self.reset = gui.add_button("reset pose")
        with gui.add_folder("Model"):
            on = bool(s.avatar.corrector.enabled)
            self.corrector = gui.add_checkbox("appearance corrector (F_a)", on, disabled=not s.has_corrector)
            on = bool(s.avatar.deformer.enabled)
            self.residual = gui.add_checkbox("weight residual (F_dw)", on, disabled=not s.has_residual)
            backends = sorted(set(s.available_backends()) | {s.backend})
            self.backend = gui.add_dropdown("rasterizer", backends, initial_value=s.backend)
            self.resolution = gui.add_slider("resolution (px)", 64, 1024, 32, self.max_side)

        self.motion.on_update(lambda _: self._guarded(self._on_motion))
        self.frame.on_update(lambda _: self._guarded(lambda: s.select(frame=int(self.frame.value))))
        self.play.on_update(lambda _: self._redraw())
        self.load.on_click(lambda _: self._guarded(self._on_load))
        self.joint.on_update(lambda _: self._guarded(self._on_joint))
        for slider in self.rotation:
            slider.on_update(lambda _: self._guarded(self._on_rotation))
        self.reset.on_click(lambda _: self._guarded(self._on_reset))
        self.corrector.on_update(lambda _: self._guarded(lambda: s.set_corrector(self.corrector.value)))
        self.residual.on_update(lambda _: self._guarded(lambda: s.set_residual(self.residual.value)))
        self.backend.on_update(lambda _: self._guarded(lambda: s.set_backend(self.backend.value)))
        self.resolution.on_update(lambda _: self._guarded(self._on_resolution))

    def _guarded(self, action) -> None:
        """Run a widget's action unless the change came from `_sync`; show a user error as a notification."""
        if getattr(self._local, "syncing", False):
            return
        try:
            action()
        except SplatrigError as exc:
            for client in self.server.get_clients().values():
                client.add_notification("splatrig", str(exc), color="red")
        self._redraw()

    def _sync(self, widget, value) -> None:
        self._local.syncing = True  # viser runs on_update callbacks synchronously on assignment
        try:
            widget.value = value
        finally:
            self._local.syncing = False

    def _on_motion(self) -> None:
        self.session.select(self.motion.value, 0)
        self.frame.max = max(self.session.num_frames - 1, 0)
        self._sync(self.frame, 0)

    def _on_load(self) -> None:
        name = self.session.add_motion_file(self.motion_file.value.strip())
        self.motion.options = list(self.session.motions)
        self._sync(self.motion, name)
        self._on_motion()

    def _joint_index(self) -> int:
        return self.session.joint_names.index(self.joint.value)

    def _on_joint(self) -> None:
        degrees = np.degrees(self.session.offsets[self._joint_index()])
        for slider, value in zip(self.rotation, degrees, strict=True):
            self._sync(slider, float(round(value)))

    def _on_rotation(self) -> None:
        self.session.set_offset(self._joint_index(), [slider.value for slider in self.rotation])

    def _on_reset(self) -> None:
        self.session.reset_offsets()
        for slider in self.rotation:
            self._sync(slider, 0)

    def _on_resolution(self) -> None:
        self.max_side = int(self.resolution.value)

    # ------------------------------------------------------------------------------------------------ rendering
    def _on_connect(self, client) -> None:
        client.camera.on_update(lambda _: self._redraw(client.client_id))
        self._redraw(client.client_id)

    def _redraw(self, client_id: int | None = None) -> None:
        with self._dirty_lock:
            if client_id is None:
                self._dirty.update(self.server.get_clients())
            else:
                self._dirty.add(client_id)
        self._wake.set()

    def _render_client(self, client) -> None:
        camera = client.camera
        try:
            aspect = camera.aspect
            wxyz, position, fov = camera.wxyz, camera.position, camera.fov
        except (AssertionError, ZeroDivisionError):  # the browser has not reported its camera yet
            return
        width, height = render_size(aspect, self.max_side)
        image = self.session.render(viser_camera(wxyz, position, fov, width, height))
        with warnings.catch_warnings():  # a browser that closed meanwhile just misses this frame
            warnings.filterwarnings("ignore", message="Queued a .* on a closed connection")
            client.scene.set_background_image(image, format="jpeg", jpeg_quality=90)
        stats = self.session.last
        fps = 1.0 / max(stats.seconds, 1e-6)
        self.status.content = (
            f"**{fps:.1f}** fps · **{stats.num_gaussians}** Gaussians · "
            f"{stats.width}×{stats.height} px · {self.session.backend} · "
            f"frames served: {stats.served}"
        )

    def _advance(self, elapsed: float) -> None:
        s = self.session
        step = max(1, round(elapsed * s.fps))
        s.select(frame=(s.frame + step) % s.num_frames)
        self._sync(self.frame, s.frame)
        self._redraw()

    def run(self) -> None:
        """Render whatever changed until `stop()` (or Ctrl-C)."""
        last = time.perf_counter()
        while not self._stop.is_set():
            playing = bool(self.play.value) and self.session.num_frames > 1
            self._wake.wait(timeout=1.0 / self.session.fps if playing else 0.25)
            self._wake.clear()
            now = time.perf_counter()
            if playing and now - last >= 1.0 / self.session.fps:
                self._advance(now - last)
                last = now
            elif not playing:
                last = now
            with self._dirty_lock:
                todo, self._dirty = self._dirty, set()
            for client_id, client in list(self.server.get_clients().items()):
                if client_id in todo:
                    try:
                        self._render_client(client)
                    except Exception as exc:  # keep serving: a failing backend must not take the page down
                        traceback.print_exc()
                        client.add_notification("render failed", f"{type(exc).__name__}: {exc}", color="red")

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        self.server.stop()

"""`python -m framework.view ckpt=...`: an interactive web viewer of a trained avatar (open the printed address).

Orbit the camera with the mouse; scrub or play the training motion, the held-out motion or a motion file; pose joints
by hand; switch the appearance corrector, the weight residual and the rasterizer; watch frames per second and the
Gaussian count. The page is served by viser on `host:port` (localhost by default); see framework/viewer/.
"""

from __future__ import annotations

from framework.errors import reported_as_message


def main() -> int:
    from omegaconf import DictConfig

    from framework.cli import hydra_main

    @hydra_main("view")
    def _main(cfg: DictConfig) -> None:
        from framework.animation.camera_paths import subject_view
        from framework.lightning.trained_model import data_overrides, datamodule_for, load_module
        from framework.runtime import default_device
        from framework.viewer.app import ViewerApp
        from framework.viewer.session import ViewerSession

        with reported_as_message():
            device = cfg.device or default_device()
            module = load_module(cfg.ckpt, map_location=str(device))
            dm = datamodule_for(module, data_overrides(cfg))
            session = ViewerSession(module, dm, cfg.motion, float(cfg.fps), cfg.rasterizer)
            app = ViewerApp(session, str(cfg.host), int(cfg.port), int(cfg.resolution), subject_view(module, dm))
            print(
                f"[splatrig] viewer at http://{cfg.host}:{app.port}  ({session.avatar.gaussians.num} Gaussians, "
                f"rasterizer {session.backend}; Ctrl-C to stop)",
                flush=True,
            )
            try:
                app.run()
            except KeyboardInterrupt:
                pass
            finally:
                app.stop()

    _main()
    return 0


if __name__ == "__main__":
    main()

"""`python -m framework.export ckpt=... motion=...`: the avatar as a standard 3D Gaussian splatting PLY (any frame, a
pose file, or the canonical pose) and, with `animatable=true`, as a package an engine can skin (framework.formats).

    python -m framework.export ckpt=<run>/checkpoints/final.ckpt              # <run>/export/canonical.ply
    python -m framework.export ckpt=... motion=novel_pose frame=10             # one posed frame
    python -m framework.export ckpt=... motion=dance.bvh animatable=true       # + <run>/export/dance_animatable/
    python -m framework.export ckpt=... prune=true    # prune + bake first (framework.prune), export the compact model
"""

from __future__ import annotations

import sys
from pathlib import Path

from framework.errors import reported_as_message
from framework.paths import beside_checkpoint


def main() -> int:
    from omegaconf import DictConfig

    from framework.cli import hydra_main

    @hydra_main("export")
    def _main(cfg: DictConfig) -> None:
        import numpy as np
        import torch

        from framework.animation.frames import posed_gaussians
        from framework.animation.package import animatable_package
        from framework.animation.sources import load_motion
        from framework.data.motion_files import Motion
        from framework.errors import SplatrigError
        from framework.formats.animatable import write_package
        from framework.formats.splat_ply import write_splat_ply
        from framework.lightning.trained_model import data_overrides, datamodule_for, load_module

        with reported_as_message():
            ckpt = str(cfg.ckpt)
            spec = export_motion(cfg)
            if cfg.prune:
                from framework.compaction.compact import prune_checkpoint
                from framework.config_checks import check_prune_config

                check_prune_config(cfg)
                report = prune_checkpoint(
                    ckpt,
                    fold_tolerance=cfg.fold_tolerance,
                    prune_tolerance=cfg.prune_tolerance,
                    refit_steps=int(cfg.refit_steps),
                    prune_rounds=int(cfg.prune_rounds),
                    timing_rasterizer=cfg.timing_rasterizer,
                )
                print(report.summary())
                ckpt = report.out
            module = load_module(ckpt)
            module.eval()
            out = Path(cfg.out_dir) if cfg.out_dir else beside_checkpoint(ckpt, "export")
            body = module.avatar.body
            if spec == "canonical":
                gaussians = module.avatar.gaussians.gaussians()
                ply = write_splat_ply(out / "canonical.ply", gaussians)
                J = 0 if body is None else body.num_joints
                motion, frames = Motion(np.zeros((1, J, 3), np.float32), None, float(cfg.fps), "canonical"), [-1]
            else:
                motion, frames = load_motion(module, datamodule_for(module, data_overrides(cfg)), spec, float(cfg.fps))
                i = int(cfg.frame)
                if not 0 <= i < motion.num_frames:
                    raise SplatrigError(f"frame={i}: motion '{spec}' has frames 0..{motion.num_frames - 1}.")
                root = None if motion.roots is None else torch.as_tensor(motion.roots[i])
                gaussians = posed_gaussians(module, torch.as_tensor(motion.poses[i]), root, frames[i])
                ply = write_splat_ply(out / f"{Path(spec).stem}_frame{i:05d}.ply", gaussians)
            print(f"[splatrig] wrote {gaussians.num} Gaussians (3DGS PLY) to {ply}")
            if cfg.animatable:
                package = animatable_package(module, motion, frames, bool(cfg.corrections))
                folder = write_package(out / f"{Path(spec).stem}_animatable", package)
                print(f"[splatrig] wrote the animatable package ({package.num_frames} frames) to {folder}")

    _main()
    return 0


def export_motion(cfg) -> str:
    """`motion=`, the same key as render's and view's; `pose=`, its older name, prints a note."""
    if cfg.get("pose") is None:
        return str(cfg.motion)
    from framework.errors import SplatrigError

    if str(cfg.motion) not in ("canonical", str(cfg.pose)):
        raise SplatrigError(
            f"motion={cfg.motion} and pose={cfg.pose}: two motions to export. Pass only motion= "
            "(pose= is its older name)."
        )
    print("[splatrig] note: pose= is the older name of motion=; write motion=" + str(cfg.pose), file=sys.stderr)
    return str(cfg.pose)


if __name__ == "__main__":
    main()

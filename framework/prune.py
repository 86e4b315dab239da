"""`python -m framework.prune ckpt=PATH [out=PATH] [min_weight=...] [sh_tolerance=...]`: a compact model for inference.

Removes Gaussians whose blending weight never reaches `min_weight` over the training views and poses, drops SH bands
whose colour change is negligible, bakes F_dw into per-Gaussian weights, folds F_a into the Gaussians when the
training frames render within `fold_tolerance` RMS colour without it, removes more Gaussians (the least needed per
pixel they cover first) while they stay within `prune_tolerance` and, if F_a was kept, folds it for as many Gaussians
as `fold_tolerance` allows; with `refit_steps`, refits the remaining Gaussians to the training images; then prints
Gaussians, size, render fps and PSNR before and after (`framework.compaction.compact`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as framework.train: no spinning OpenMP threads on a busy CPU

from omegaconf import DictConfig

from framework.errors import reported_as_message


def prune_from_config(cfg: DictConfig):
    """What `python -m framework.prune` does with its composed config; returns the `PruneReport`."""
    from framework.compaction.compact import prune_checkpoint
    from framework.config_checks import check_prune_config

    check_prune_config(cfg)
    report = prune_checkpoint(
        cfg.ckpt,
        cfg.out,
        min_weight=float(cfg.min_weight),
        sh_tolerance=float(cfg.sh_tolerance),
        max_frames=cfg.max_frames,
        measure=bool(cfg.measure),
        warmup=int(cfg.warmup),
        repeats=int(cfg.repeats),
        rounds=int(cfg.rounds),
        device=cfg.device,
        fold_tolerance=cfg.fold_tolerance,
        prune_tolerance=cfg.prune_tolerance,
        refit_steps=int(cfg.refit_steps),
        prune_rounds=int(cfg.prune_rounds),
        timing_rasterizer=cfg.timing_rasterizer,
    )
    print(report.summary())
    if cfg.json:
        Path(cfg.json).write_text(json.dumps(report.to_dict(), indent=1))
    return report


def main() -> None:
    from framework.cli import hydra_main

    @hydra_main("prune")
    def _main(cfg: DictConfig) -> None:
        with reported_as_message():
            prune_from_config(cfg)

    _main()


if __name__ == "__main__":
    main()

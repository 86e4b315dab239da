"""`python -m framework.train +experiment=NAME [overrides]`: compose, build, train, evaluate, report.

Prints where the run's results are and returns the configured metric so Hydra sweepers can optimise it.
"""

from __future__ import annotations

import os
import sys

# torch's OpenMP threads spin-wait by default; on a busy 2-core machine that starves the other thread (measured 3-10x
# slower steps). Must be set before torch is imported; an explicit user setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from framework.errors import SplatrigError, reported_as_message

CONFIG_PATH = "pkg://framework.conf"


def choose_profile(argv: list[str]) -> list[str]:
    """Add `profile=gpu|cpu` unless the user chose one: the same command adapts to the machine it runs on."""
    if any(a.split("=")[0].lstrip("+~") == "profile" for a in argv[1:]):
        return argv
    import torch

    profile = "gpu" if torch.cuda.is_available() else "cpu"
    why = "a CUDA device is available" if profile == "gpu" else "no CUDA device was found"
    print(f"[splatrig] profile={profile} ({why}); override with profile=cpu|gpu", file=sys.stderr)
    added = [f"profile={profile}"]
    chose_rasterizer = any(a.split("=")[0].lstrip("+~") == "rasterizer" for a in argv[1:])
    if profile == "gpu" and not chose_rasterizer:
        import importlib.util

        if importlib.util.find_spec("gsplat") is not None:
            added.append("rasterizer=gsplat")
            print("[splatrig] rasterizer=gsplat (CUDA kernels); override with rasterizer=torch_ref", file=sys.stderr)
    # argparse wants Hydra's overrides in one run: put ours just before the first one (or last when there are none)
    first = next((i for i, a in enumerate(argv[1:], 1) if "=" in a and not a.startswith("-")), len(argv))
    return [*argv[:first], *added, *argv[first:]]


def quiet_libraries() -> None:
    """Lightning's banners (GPU/TPU availability, tips) would bury our own progress and result lines."""
    import logging
    import warnings

    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        logging.getLogger(name).setLevel(logging.WARNING)
    warnings.filterwarnings("ignore", message=".*isinstance\\(treespec, LeafSpec\\).*")
    warnings.filterwarnings("ignore", message=".*does not have many workers.*")
    # We checkpoint after the optimizer step on purpose: a resumed run continues from the state after that step.
    warnings.filterwarnings("ignore", message=".*ModelCheckpoint with manual optimization.*")


def run(cfg: DictConfig) -> float | None:
    import lightning as L
    import torch
    from lightning.pytorch.callbacks import ModelCheckpoint
    from lightning.pytorch.loggers import TensorBoardLogger

    from framework.build import build_component
    from framework.config_checks import check_train_config
    from framework.evaluate import evaluate_module
    from framework.lightning.callbacks import ImageGridLogger, StageSwitch, StepProgressBar
    from framework.lightning.checkpoint_io import AtomicCheckpointIO
    from framework.lightning.data import FrameDataModule
    from framework.lightning.module import SplatModule
    from framework.plugins import load_plugins

    check_train_config(cfg)
    load_plugins()
    quiet_libraries()
    out_dir = Path(cfg.paths.output_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "config_resolved.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    torch.set_float32_matmul_precision("high")
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))

    container: dict[str, Any] = OmegaConf.to_container(cfg, resolve=True)  # type: ignore[assignment]

    def build_split(split: str):
        return build_component("dataset", cfg.data, group="data", split=split)

    dm = FrameDataModule(
        build_split,
        val_split=str(cfg.eval.val_split),
        val_max_items=int(cfg.eval.val_max_items),
        num_workers=int(cfg.data_loader.num_workers),
        seed=int(cfg.seed),
    )
    train_set = dm.train_set
    poses = train_set.poses()
    data_info = {
        "bounds": train_set.bounds.tolist(),
        "num_frames_total": int(train_set.num_frames_total),
        "body_name": train_set.body_name,
        "num_joints": None if poses is None else int(poses.shape[1]),
        "betas": None if train_set.fitted_betas() is None else train_set.fitted_betas().tolist(),
    }
    module = SplatModule(container, data_info)

    logger = TensorBoardLogger(save_dir=str(out_dir), name="tb", version="") if cfg.logger.name else None
    ckpt_dir = out_dir / "checkpoints"
    callbacks = [
        ModelCheckpoint(
            dirpath=ckpt_dir,
            filename="best",
            monitor="val/psnr",
            mode="max",
            save_last=True,
            save_top_k=1,
            auto_insert_metric_name=False,
        ),  # fmt: skip
        ModelCheckpoint(
            dirpath=ckpt_dir,
            filename="last",
            every_n_train_steps=int(cfg.callbacks.checkpoint_every),
            save_top_k=1,
            enable_version_counter=False,
        ),  # fmt: skip
        StageSwitch(int(cfg.stages.stage1_steps)),
        ImageGridLogger(int(cfg.callbacks.image_every), int(cfg.callbacks.image_views)),
    ]
    if cfg.callbacks.progress_bar:
        callbacks.append(StepProgressBar())
    trainer = L.Trainer(
        max_steps=int(cfg.trainer.max_steps),
        max_time=cfg.trainer.get("max_time"),
        accelerator=str(cfg.trainer.accelerator),
        devices=1,
        precision=cfg.trainer.precision,
        logger=logger,
        callbacks=callbacks,
        val_check_interval=int(cfg.trainer.val_every),
        check_val_every_n_epoch=None,
        num_sanity_val_steps=0,
        log_every_n_steps=int(cfg.trainer.log_every),
        enable_progress_bar=False,
        enable_model_summary=False,
        deterministic=False,
        fast_dev_run=bool(cfg.trainer.get("fast_dev_run", False)),
        limit_val_batches=cfg.trainer.get("limit_val_batches", 1.0),
        plugins=[AtomicCheckpointIO()],  # a kill during a save leaves the previous checkpoint intact
    )
    ckpt_path = cfg.get("ckpt_path")
    if ckpt_path is not None and not Path(ckpt_path).is_file():
        raise SplatrigError(f"ckpt_path={ckpt_path}: no such checkpoint file. Point it at a run's "
                            f"checkpoints/last.ckpt (or best.ckpt).")  # fmt: skip
    trainer.fit(module, datamodule=dm, ckpt_path=ckpt_path, weights_only=False)

    if module.bake_weights():
        trainer.save_checkpoint(ckpt_dir / "final.ckpt", weights_only=False)
        print(f"[splatrig] blend weights baked into each Gaussian: {ckpt_dir / 'final.ckpt'} needs no weight MLP")
    result: dict[str, float] = {}
    if cfg.eval.after_fit and not cfg.trainer.get("fast_dev_run", False):
        result = evaluate_module(module, dm, list(cfg.eval.splits), list(cfg.eval.metrics), out_dir / "eval",
                                 logger=logger, step=trainer.global_step)  # fmt: skip
    print(f"\n[splatrig] results: {out_dir}")
    print(f"[splatrig]   checkpoints: {ckpt_dir}  (resume with ckpt_path={ckpt_dir / 'last.ckpt'})")
    print(f"[splatrig]   tensorboard: tensorboard --logdir {out_dir / 'tb'}")
    if result:
        print(f"[splatrig]   metrics: {out_dir / 'eval'}")
    metric = str(cfg.metric)
    if metric in result:
        return float(result[metric])
    logged = trainer.callback_metrics.get(metric)
    return None if logged is None else float(logged)


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="train")
def _hydra_main(cfg: DictConfig) -> float | None:
    with reported_as_message():
        return run(cfg)


def main() -> None:
    sys.argv = choose_profile(sys.argv)
    _hydra_main()


if __name__ == "__main__":
    main()

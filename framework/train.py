"""`python -m framework.train +experiment=NAME [overrides]`: compose, build, train, evaluate, report.

Prints where the run's results are and returns the configured metric so Hydra sweepers can optimise it.
"""

from __future__ import annotations

import functools
import os
import sys
import time

# torch's OpenMP threads spin-wait by default; on a busy machine with few cores that starves the other threads (steps
# several times slower). Must be set before torch is imported; an explicit user setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from framework.cli import hydra_main
from framework.errors import SplatrigError, reported_as_message


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


def reset_peak_memory() -> None:
    """Start the peak-memory counters afresh, so the fit loop's peak is not the data preparation's (Linux: writing
    5 to /proc/self/clear_refs resets the resident-set high-water mark VmHWM)."""
    import torch

    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass
    if torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()


def _peak_rss_mib() -> float:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024  # kB
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB (whole process lifetime)


def write_train_stats(path: Path, fit_seconds: float, steps: int, num_gaussians: int) -> dict:
    """Training cost for comparisons (tools/scene_adaptive.py): wall time of the fit loop (data preparation and the
    final evaluation excluded), the peak resident memory since `reset_peak_memory` and, on CUDA, peak allocated
    device memory."""
    import json

    import torch

    stats = {
        "fit_seconds": round(fit_seconds, 2),
        "steps": int(steps),
        "num_gaussians": int(num_gaussians),
        "peak_rss_mib": round(_peak_rss_mib(), 1),
        "cuda_peak_mib": round(torch.cuda.max_memory_allocated() / 2**20, 1) if torch.cuda.is_available() else None,
    }
    path.write_text(json.dumps(stats, indent=1))
    return stats


def resume_checkpoint(cfg: DictConfig) -> str | None:
    """The checkpoint to resume from, `ckpt=` (`ckpt_path=`, its older name, prints a note), checked before anything
    is built."""
    ckpt, old = cfg.ckpt, cfg.ckpt_path
    if old is not None:
        if ckpt is not None and str(ckpt) != str(old):
            raise SplatrigError(
                f"ckpt={ckpt} and ckpt_path={old}: two checkpoints to resume from. Pass only ckpt= "
                "(ckpt_path= is its older name)."
            )
        print(f"[splatrig] note: ckpt_path= is the older name of ckpt=; write ckpt={old}", file=sys.stderr)
        ckpt = old
    if ckpt is not None and not Path(str(ckpt)).is_file():
        raise SplatrigError(f"ckpt={ckpt}: no such checkpoint file. Point it at a run's checkpoints/last.ckpt.")
    return None if ckpt is None else str(ckpt)


def run(cfg: DictConfig, overrides: list[str] | None = None) -> float | None:
    """Train (and evaluate) the composed `cfg`. `overrides`: the overrides it was composed with, so `+scene=auto`
    leaves alone what the user set (default: this Hydra job's command line; a caller that composes the config itself,
    such as tools/bench_train.py, has no Hydra job and passes its own)."""
    ckpt_path = resume_checkpoint(cfg)  # a file check: before the libraries load, the data is opened or a model built
    import lightning as L
    import torch
    from lightning.pytorch.callbacks import ModelCheckpoint
    from lightning.pytorch.loggers import TensorBoardLogger

    from framework.build import build_split
    from framework.config_checks import check_train_config
    from framework.evaluate import evaluate_module
    from framework.evaluation.run_cost import run_cost
    from framework.evaluation.run_record import metrics_from_summary, write_run_record
    from framework.lightning.callbacks import ImageGridLogger, StageSwitch, StepProgressBar
    from framework.lightning.checkpoint_io import AtomicCheckpointIO
    from framework.lightning.data import FrameDataModule
    from framework.lightning.module import SplatModule
    from framework.plugins import load_plugins
    from framework.runtime import reuse_freed_memory
    from framework.scene.setup import command_line_overrides, prepare_scene

    check_train_config(cfg)
    reuse_freed_memory()
    started = time.perf_counter()
    load_plugins()
    quiet_libraries()
    out_dir = Path(cfg.paths.output_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    # float32 matrix products stay float32 on a GPU: "high" would let them round to TF32's 10-bit mantissa, which moves
    # the LBS blend's translations by ~1.5 mm (tools/emulate_tf32.py). Convolutions: framework.runtime.exact_float32.
    torch.set_float32_matmul_precision("highest")
    if cfg.threads:
        torch.set_num_threads(cfg.threads)

    dm = FrameDataModule(
        functools.partial(build_split, cfg.data),
        val_split=str(cfg.eval.val_split),
        val_max_items=int(cfg.eval.val_max_items),
        num_workers=int(cfg.data_loader.num_workers),
        seed=int(cfg.seed),
    )
    train_set = dm.train_set
    # the scene survey and `+scene=auto` may change the config, so it is resolved and saved after them
    user_overrides = command_line_overrides() if overrides is None else overrides
    scene = prepare_scene(cfg, train_set, user_overrides, progress=bool(cfg.callbacks.progress_bar))
    (out_dir / "config_resolved.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    if scene.survey is not None or scene.frozen_pose:
        (out_dir / "scene.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(scene.summary())))
    container: dict[str, Any] = OmegaConf.to_container(cfg, resolve=True)  # type: ignore[assignment]
    poses = train_set.poses()
    data_info = {
        "bounds": train_set.bounds.tolist(),
        "num_frames_total": int(train_set.num_frames_total),
        "body_name": train_set.body_name,
        "num_joints": None if poses is None else int(poses.shape[1]),
        "betas": None if train_set.fitted_betas() is None else train_set.fitted_betas().tolist(),
    }
    if scene.frozen_pose:
        data_info["frozen_pose"] = scene.frozen_pose
    module = SplatModule(container, data_info)

    logger = TensorBoardLogger(save_dir=str(out_dir), name="tb", version="") if cfg.logger.name else None
    if logger is not None:
        scene.log(logger.experiment)
    ckpt_dir = out_dir / "checkpoints"
    # No "best" checkpoint: validation runs on a test split (novel views), and a model chosen on test data would
    # report optimistic test numbers. We keep the model training ends with: last.ckpt (also saved periodically, to
    # resume) and final.ckpt (blend weights baked).
    callbacks = [
        ModelCheckpoint(
            dirpath=ckpt_dir,
            filename="last",
            every_n_train_steps=int(cfg.callbacks.checkpoint_every),
            save_top_k=1,
            enable_version_counter=False,
        ),
        stage_switch := StageSwitch(int(cfg.stages.stage1_steps)),
        ImageGridLogger(int(cfg.callbacks.image_every), int(cfg.callbacks.image_views)),
    ]
    if cfg.callbacks.progress_bar:
        callbacks.append(StepProgressBar())
    trainer = L.Trainer(
        max_steps=int(cfg.trainer.max_steps),
        max_time=cfg.trainer.max_time,
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
        fast_dev_run=cfg.trainer.fast_dev_run,
        limit_val_batches=cfg.trainer.limit_val_batches,
        plugins=[AtomicCheckpointIO()],  # a kill during a save leaves the previous checkpoint intact
    )
    reset_peak_memory()
    fit_started, fit_cpu = time.perf_counter(), time.process_time()
    trainer.fit(module, datamodule=dm, ckpt_path=ckpt_path, weights_only=False)
    train_seconds, train_cpu_seconds = time.perf_counter() - fit_started, time.process_time() - fit_cpu
    # Lightning's teardown moved the module to the CPU: bake, evaluate and time it on the device it trained on
    module.to(trainer.strategy.root_device)
    train_stats = write_train_stats(
        out_dir / "train_stats.json", train_seconds, trainer.global_step, module.avatar.gaussians.num
    )
    trainer.save_checkpoint(ckpt_dir / "last.ckpt", weights_only=False)  # the end state, whatever the save period

    final = ckpt_dir / "last.ckpt"
    if module.bake_weights():
        final = ckpt_dir / "final.ckpt"
        trainer.save_checkpoint(final, weights_only=False)
        print(f"[splatrig] blend weights baked into each Gaussian: {final} needs no weight MLP")
    result: dict[str, float] = {}
    evaluating = cfg.eval.after_fit and not cfg.trainer.fast_dev_run
    if evaluating:
        result = evaluate_module(
            module,
            dm,
            list(cfg.eval.splits),
            list(cfg.eval.metrics),
            out_dir / "eval",
            logger=logger,
            step=trainer.global_step,
        )
    fps_frames = cfg.eval.fps_frames if evaluating else 0
    cost = run_cost(module, dm, final, train_seconds, int(trainer.global_step), fps_frames, cfg.eval.fps_warmup)
    config_name, overrides = _hydra_job()
    record = write_run_record(
        out_dir,
        experiment=str(cfg.task_name),
        config_name=config_name,
        overrides=overrides,
        seed=int(cfg.seed),
        profile=str(cfg.profile.name),
        data=str(cfg.data.name),
        steps=int(trainer.global_step),
        max_steps=int(cfg.trainer.max_steps),
        train_seconds=round(train_seconds, 2),
        train_cpu_seconds=round(train_cpu_seconds, 2),
        run_seconds=round(time.perf_counter() - started, 2),
        num_gaussians=int(module.avatar.gaussians.num),
        peak_rss_mib=train_stats["peak_rss_mib"],
        cuda_peak_mib=train_stats["cuda_peak_mib"],
        stage_seconds=stage_switch.stage_seconds(),
        **cost,
        metrics=metrics_from_summary(result),
    )
    print(f"\n[splatrig] results: {out_dir}")
    print(f"[splatrig]   checkpoints: {ckpt_dir}  (resume with ckpt={ckpt_dir / 'last.ckpt'})")
    print(f"[splatrig]   tensorboard: tensorboard --logdir {out_dir / 'tb'}")
    if result:
        print(f"[splatrig]   metrics: {out_dir / 'eval'}, {record}")
    metric = str(cfg.metric)
    if metric in result:
        return float(result[metric])
    logged = trainer.callback_metrics.get(metric)
    return None if logged is None else float(logged)


def _hydra_job() -> tuple[str | None, list[str]]:
    """(primary config name, this job's overrides) as Hydra knows them; (None, []) outside a Hydra run."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None, []
    hc = HydraConfig.get()
    return hc.job.config_name, list(hc.overrides.task)


@hydra_main("train")
def _hydra_main(cfg: DictConfig) -> float | None:
    with reported_as_message():
        return run(cfg)


def main() -> None:
    sys.argv = choose_profile(sys.argv)
    _hydra_main()


if __name__ == "__main__":
    main()

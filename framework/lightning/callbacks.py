"""Callbacks: a step-based progress bar with ETA, TensorBoard image grids, and the two-stage switch."""

from __future__ import annotations

import time

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback
from tqdm.auto import tqdm

from framework.lightning.data import collate_frames
from framework.lightning.host_copy import HostCopy


class StepProgressBar(Callback):
    """Counts optimisation steps toward `max_steps` (epochs mean nothing here), with ETA, loss, PSNR and N."""

    def __init__(self, refresh_every: int = 10) -> None:
        self.refresh_every = refresh_every
        self.bar: tqdm | None = None
        self._pending: HostCopy | None = None  # loss and PSNR of a refresh, on their way to the host

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.bar = tqdm(
            total=trainer.max_steps,
            initial=trainer.global_step,
            desc="training",
            unit="it",
            dynamic_ncols=True,
            smoothing=0.05,
        )

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self.bar is None:
            return
        self.bar.update(trainer.global_step - self.bar.n)
        if trainer.global_step % self.refresh_every == 0:
            # the values of this refresh are shown once they reach the host, without waiting for the device: at once
            # on a CPU, at the next refresh or later on a GPU
            loss = outputs["loss"] if isinstance(outputs, dict) else outputs
            psnr = getattr(pl_module, "last_train_psnr", None)
            latest = HostCopy([loss, loss.new_zeros(()) if psnr is None else psnr])
            landed = next((c for c in (latest, self._pending) if c is not None and c.ready()), None)
            if landed is not None:
                shown_loss, shown_psnr = (float(v.numpy()) for v in landed.values())
                self.bar.set_postfix(
                    loss=f"{shown_loss:.4f}", psnr=f"{shown_psnr:.2f}", n=pl_module.avatar.gaussians.num, refresh=False
                )
            self._pending = None if latest.ready() else latest

    def on_train_end(self, trainer, pl_module) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


class ImageGridLogger(Callback):
    """Every `every` steps: render | ground truth | error for a few held-out views, into TensorBoard."""

    def __init__(self, every: int = 500, num_views: int = 2) -> None:
        self.every = every
        self.num_views = num_views

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        step = trainer.global_step
        if self.every <= 0 or step % self.every != 0 or trainer.logger is None:
            return
        writer = getattr(trainer.logger, "experiment", None)
        if writer is None or not hasattr(writer, "add_image"):
            return
        dm = trainer.datamodule
        dataset = dm.split(dm.val_split)
        if len(dataset) == 0:
            return
        idx = torch.linspace(0, len(dataset) - 1, min(self.num_views, len(dataset))).round().long().tolist()
        rows = []
        with torch.no_grad():
            for i in idx:
                sample = collate_frames([dataset[i]]).to(pl_module.device)
                rgb = pl_module.render_batch(sample).render.rgb[0].clamp(0, 1)
                gt = sample.image[0]
                err = (rgb - gt).abs().mean(-1, keepdim=True).expand_as(rgb).clamp(0, 1) * 4
                rows.append(torch.cat([rgb, gt, err.clamp(0, 1)], dim=1))
        grid = torch.cat(rows, dim=0)  # [H*views, 3W, 3]
        writer.add_image("val/render|gt|error", grid.permute(2, 0, 1).cpu(), step)


class StageSwitch(Callback):
    """Stage 1 trains Gaussians and joints only; at `stage1_steps` the corrector and weight residual switch on and the
    module is told (`begin_stage2`), which restarts the densifier's opacity-reset count as the paper schedules it."""

    def __init__(self, stage1_steps: int = 0) -> None:
        self.stage1_steps = stage1_steps
        self._clock: list[tuple[int, float]] = []  # (global step, wall seconds) at the start, the switch and the end

    def _mark(self, trainer) -> None:
        """Wall clock at a stage boundary, after the device has finished what was queued (once per boundary)."""
        if torch.cuda.is_available() and trainer.strategy.root_device.type == "cuda":
            torch.cuda.synchronize()
        self._clock.append((int(trainer.global_step), time.perf_counter()))

    def stage_seconds(self) -> dict[str, dict[str, float]]:
        """{"stage1"|"stage2": {"steps", "seconds", "steps_per_second"}} of this fit (validation included)."""
        out = {}
        marks = self._clock
        for (step0, t0), (step1, t1) in zip(marks, marks[1:], strict=False):
            if step1 > step0:
                name = "stage2" if step0 >= self.stage1_steps else "stage1"
                out[name] = {
                    "steps": step1 - step0,
                    "seconds": round(t1 - t0, 2),
                    "steps_per_second": round((step1 - step0) / max(t1 - t0, 1e-9), 2),
                }
        return out

    def _apply(self, trainer, pl_module) -> None:
        stage2 = trainer.global_step >= self.stage1_steps
        avatar = pl_module.avatar
        changed = False
        for part in (avatar.corrector, avatar.deformer):
            if part.enabled != stage2:
                part.enabled = stage2
                changed = True
        if self.stage1_steps > 0 and trainer.global_step == self.stage1_steps:
            pl_module.begin_stage2(trainer.global_step)
        if changed and stage2 and trainer.global_step > 0:
            tqdm.write(f"[splatrig] step {trainer.global_step}: stage 2, corrector and blend-weight residual on")
        if getattr(pl_module, "logs_this_step", lambda: True)():
            pl_module.log("train/stage", 2.0 if stage2 else 1.0, on_step=True, batch_size=1)

    def on_train_start(self, trainer, pl_module) -> None:
        stage2 = trainer.global_step >= self.stage1_steps
        for part in (pl_module.avatar.corrector, pl_module.avatar.deformer):
            part.enabled = stage2
        self._clock = []
        self._mark(trainer)

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if trainer.global_step == self.stage1_steps and self._clock and self._clock[-1][0] < self.stage1_steps:
            self._mark(trainer)
        self._apply(trainer, pl_module)

    def on_train_end(self, trainer, pl_module) -> None:
        self._mark(trainer)

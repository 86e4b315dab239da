"""The LightningModule: builds the avatar from the registries and runs one manually-optimised step per batch.

Manual optimisation with ONE optimizer (one named param group per parameter kind) keeps `global_step` equal to the
number of training iterations (Lightning counts every wrapped `optimizer.step()`), and lets the densifier resize
parameters and their Adam state between steps.
"""

from __future__ import annotations

import functools
import math
import sys
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch import Tensor, nn

from framework.build import ConfigError, build_component, node_kwargs, with_fitted_betas
from framework.config_schema import Train, training_settings
from framework.execution import Execution
from framework.guards import PSNR_MSE_FLOOR
from framework.lightning.deferred_checks import DeferredChecks, defers
from framework.lightning.divergence import (
    DivergencePolicy,
    TrainingDiverged,
    diagnose,
    finite_probe,
    grads_and_params,
)
from framework.model.avatar import GAUSSIAN_KEYS, Avatar, GaussianParams, PoseRefiner
from framework.model.losses import CompositeLoss
from framework.runtime import cpu_threads, default_device
from framework.types import FrameBatch, Gaussians


def psnr(pred: Tensor, target: Tensor) -> Tensor:
    mse = ((pred - target) ** 2).flatten(1).mean(1).clamp_min(PSNR_MSE_FLOOR)
    return -10 * torch.log10(mse)


def training_device(settings: Train) -> str:
    """The device a run's config trains on: `trainer.accelerator`, where auto (or gpu) is the GPU when there is one,
    as Lightning picks it."""
    return "cpu" if settings.trainer.accelerator == "cpu" else default_device()


class SplatModule(L.LightningModule):
    def __init__(self, cfg: dict[str, Any], data_info: dict[str, Any], device: str | None = None) -> None:
        """`device`: where the model will run (default: where its config trains), which `execution.kernels: auto`
        is resolved against. `cfg` (a plain container, stored in checkpoints) is read through `self.settings`, its
        typed form (framework.config_schema: a key an older checkpoint lacks reads as its default)."""
        super().__init__()
        self.save_hyperparameters({"cfg": cfg, "data_info": data_info})
        self.automatic_optimization = False
        self.cfg = cfg
        self.settings = settings = training_settings(cfg)
        self.data_info = data_info
        try:  # how every component runs (torch, or the compiled CPU kernels): one choice, handed to each
            self.execution = Execution.resolve(settings.execution.kernels, device or training_device(settings))
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        bounds = torch.tensor(data_info["bounds"], dtype=torch.float32)  # [2, 3]
        self.scene_scale = float((bounds[1] - bounds[0]).norm() / 2)

        body = build_component("body", with_fitted_betas(cfg["body"], data_info.get("betas")))
        if body is not None and data_info.get("num_joints") not in (None, body.num_joints):
            raise ConfigError(
                f"body '{cfg['body']['name']}' has {body.num_joints} joints but the dataset's poses have "
                f"{data_info['num_joints']}. Select the body the data was made with (dataset body: "
                f"'{data_info.get('body_name')}'), e.g. `body={data_info.get('body_name')}`."
            )
        frozen = list(settings.scene.frozen_joints)
        if body is not None and frozen:  # joints still over the training frames leave the pose input and LBS sum
            from framework.model.frozen_body import FrozenJointsBody

            body = FrozenJointsBody(body, frozen, data_info.get("frozen_pose"))
        gaussians = self._initial_gaussians(body, bounds)
        corrector = build_component("corrector", cfg["corrector"])
        deformer = build_component("deformer", cfg["deformer"])
        rasterizer = build_component("rasterizer", cfg["rasterizer"])
        if body is not None:
            corrector.bind(body.num_pose_features)
            canonical_bounds = _padded_box(body.rest_vertices, 0.1)
            deformer.bind(body, canonical_bounds)
        else:
            deformer.bind(None, bounds)
        refiner = None
        if body is not None:
            refiner = PoseRefiner(int(data_info["num_frames_total"]), body.num_joints, settings.pose_refine.enabled)
        self.avatar = Avatar(
            GaussianParams(gaussians),
            rasterizer,
            corrector,
            deformer,
            body,
            refiner,
            background=tuple(settings.background),
            execution=self.execution,
        )
        self.loss_fn = CompositeLoss(cfg["loss"]["terms"], self.execution)
        deformer.use_aux(self.loss_fn.aux_keys)  # e.g. no L_w term: the deformer skips the six-point weight lookups
        self.densifier = build_component("densifier", cfg["densifier"])
        if self.densifier is not None:
            self.densifier.set_execution(self.execution)
        self.densifier_state: dict[str, Any] = (
            self.densifier.initialize_state(scene_scale=self.scene_scale) if self.densifier else {}
        )
        self._step_started = time.perf_counter()
        self._steps_since_log = 0
        self._last_train_psnr: Tensor | None = None
        self._loaded_steps = 0
        try:
            self.divergence = DivergencePolicy.from_config(settings.divergence)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        self.lr_scale = 1.0  # lowered by every divergence rollback; saved in checkpoints
        self.rollbacks = 0
        self._checks = DeferredChecks()  # the probes' verdicts a GPU step did not wait for
        self._defers_checks: bool | None = None  # decided at the first step, from the optimizer and the device

    # ----------------------------------------------------------------------------------------------- construction
    def _initial_gaussians(self, body, bounds: Tensor) -> Gaussians:
        from framework.model import gaussian_init

        g, seed = self.settings.gaussians, self.settings.seed
        if body is not None:
            return gaussian_init.from_body_surface(body, num=g.num, sh_degree=g.sh_degree, seed=seed, opacity=g.opacity)
        return gaussian_init.random_in_box(bounds, num=g.num, sh_degree=g.sh_degree, seed=seed, opacity=g.opacity)

    def configure_optimizers(self):
        lr = vars(self.settings.optim.lr)
        params = self.avatar.gaussians.params
        groups = []
        for key in GAUSSIAN_KEYS:
            if key in params and params[key].requires_grad:
                scale = self.scene_scale if key == "means" else 1.0
                groups.append({"params": [params[key]], "lr": float(lr[key]) * scale, "name": key})
        networks = [p for m in (self.avatar.corrector, self.avatar.deformer) for p in m.parameters()]
        if networks:
            groups.append({"params": networks, "lr": float(lr["networks"]), "name": "networks"})
        if self.avatar.pose_refiner is not None and self.avatar.pose_refiner.enabled:
            groups.append({"params": [self.avatar.pose_refiner.pose_residual], "lr": float(lr["pose"]), "name": "pose"})
            groups.append(
                {"params": [self.avatar.pose_refiner.joint_residual], "lr": float(lr["joints"]), "name": "joints"}
            )
        # The fused kernel updates every tensor in one pass per group (the same Adam; results agree to float rounding):
        # 3x less time than the per-parameter loop on CPU for this model. Unsupported dtypes/devices keep the loop.
        params_all = [p for g in groups for p in g["params"]]
        fused = all(p.device.type in ("cpu", "cuda") and p.dtype in (torch.float32, torch.float64) for p in params_all)
        return torch.optim.Adam(groups, eps=1e-15, fused=fused or None)

    # ------------------------------------------------------------------------------------------------- schedules
    def sh_degree(self, step: int) -> int:
        g = self.settings.gaussians
        return min(g.sh_degree, step // max(g.sh_increase_every, 1))

    def set_sh_degree(self, degree: int) -> None:
        """Render up to this SH degree from now on (compaction dropped the bands above it): config and settings."""
        self.cfg["gaussians"]["sh_degree"] = self.settings.gaussians.sh_degree = int(degree)

    def _set_learning_rates(self, optimizer: torch.optim.Optimizer, step: int) -> None:
        """3DGS: the position learning rate decays exponentially to `means_final_ratio` of its start; every rate is
        scaled by `lr_scale` (1 unless a divergence rollback lowered it)."""
        lr = vars(self.settings.optim.lr)
        total = max(self.settings.trainer.max_steps, 1)
        ratio = self.settings.optim.means_final_ratio
        t = min(step / total, 1.0)
        for group in optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = float(lr["means"]) * self.scene_scale * math.exp(t * math.log(ratio)) * self.lr_scale
            elif group["name"] in lr:
                group["lr"] = float(lr[group["name"]]) * self.lr_scale

    # ---------------------------------------------------------------------------------------------------- steps
    def trained_steps(self) -> int:
        """Steps trained so far: the trainer's count while attached, else the loaded checkpoint's (the SH degree
        and other schedules follow it, so `python -m framework.evaluate` renders what training evaluated)."""
        return self.global_step if self._trainer is not None else self._loaded_steps

    def render_batch(self, batch: FrameBatch, step: int | None = None):
        step = self.trained_steps() if step is None else step
        return self.avatar(batch, sh_degree=self.sh_degree(step))

    def training_step(self, batch: FrameBatch, batch_idx: int) -> Tensor:
        opt = self.optimizers()
        optimizer = opt.optimizer
        step = self.global_step
        log_now = self.logs_this_step()  # before opt.step(), which advances global_step
        self._set_learning_rates(optimizer, step)
        out = self.render_batch(batch, step)
        # the small work around the render and the backward on `small_work_threads` CPU threads (framework.runtime)
        small_work = functools.partial(cpu_threads, self.settings.small_work_threads, self.device)
        with small_work():
            total, terms = self.loss_fn(out.render, batch, out.aux)
            params = self.avatar.gaussians.params
            info = {
                "means2d": out.render.means2d,
                "radii": out.render.radii,
                "width": batch.cameras.width,
                "height": batch.cameras.height,
                "n_cameras": batch.cameras.num,
            }
            if self.densifier is not None:
                self.densifier.step_pre_backward(
                    params, self._densifier_optimizers(optimizer), self.densifier_state, step, info
                )
        self.manual_backward(total)
        with small_work():
            return self._update(opt, step, total, terms, out, batch, info, log_now)

    def _update(
        self,
        opt: Any,
        step: int,
        total: Tensor,
        terms: dict[str, Tensor],
        out: Any,
        batch: FrameBatch,
        info: dict[str, Any],
        log_now: bool,
    ) -> Tensor:
        """After the backward: the divergence check, the optimizer step, the densifier's bookkeeping and logging."""
        optimizer = opt.optimizer
        params = self.avatar.gaussians.params
        if self._deferred(optimizer):
            optimizer.found_inf = self._checks.probe(step, total, terms, optimizer)  # a bad update skips on the device
            try:
                opt.step()
            finally:
                del optimizer.found_inf
        else:
            grads, values = grads_and_params(optimizer)
            if not bool(torch.isfinite(finite_probe([total, *grads, *values]))):  # the step's one host sync
                self._diverged(diagnose(step, total, terms, optimizer), optimizer)
                opt.zero_grad(set_to_none=True)
                return total.detach()
            opt.step()
        opt.zero_grad(set_to_none=True)
        if self.densifier is not None:
            with torch.no_grad():
                self.densifier.step_post_backward(
                    params, self._densifier_optimizers(optimizer), self.densifier_state, step, info
                )
        if len(self._checks):
            # the verdicts of earlier steps the device has finished; all of them, waiting, before a checkpoint
            message = self._checks.first_bad(before_step=None if self._checkpoint_due(step + 1) else step)
            if message is not None:
                self._diverged(message, optimizer)
                return total.detach()
        if self._checkpoint_due(step + 1) and not bool(torch.isfinite(finite_probe(grads_and_params(optimizer)[1]))):
            message = diagnose(step, total.new_zeros(()), {}, optimizer).replace("at step", "after the update of step")
            self._diverged(message, optimizer)
        self._steps_since_log += 1
        with torch.no_grad():
            self._last_train_psnr = psnr(out.render.rgb.detach(), batch.image).mean()
        if log_now:
            now = time.perf_counter()
            ms = (now - self._step_started) * 1000 / self._steps_since_log  # mean over the steps since the last log
            self._step_started, self._steps_since_log = now, 0
            self.log_dict({f"loss/{k}": v for k, v in terms.items()}, on_step=True, batch_size=1)
            self.log("loss/total", total.detach(), on_step=True, prog_bar=False, batch_size=1)
            self.log("train/psnr", self._last_train_psnr, on_step=True, batch_size=1)
            self.log("train/num_gaussians", float(self.avatar.gaussians.num), on_step=True, batch_size=1)
            self.log("train/ms_per_iteration", ms, on_step=True, batch_size=1)
            self.log("train/sh_degree", float(self.sh_degree(step)), on_step=True, batch_size=1)
            for group in optimizer.param_groups:
                self.log(f"lr/{group['name']}", group["lr"], on_step=True, batch_size=1)
        return total.detach()

    def on_train_end(self) -> None:
        """Read the verdicts a deferred run has not read yet: training stopped by time or interruption can end on a step
        that writes no checkpoint, and train.py saves one after fit."""
        if len(self._checks):
            message = self._checks.first_bad()
            if message is not None:
                self._diverged(message, self.optimizers().optimizer)

    def logs_this_step(self) -> bool:
        """Whether Lightning writes this training step's metrics to the logger (every `log_every_n_steps`, and on the
        last step). Scalars logged on other steps would be overwritten unseen, and ~20 `self.log` calls cost tens of
        ms per step on a CPU, so training logs only on these steps."""
        trainer = self._trainer
        if trainer is None or trainer.fast_dev_run:
            return True
        every = int(trainer.log_every_n_steps)
        # Lightning's own test: (batches stepped + 1) % every; one optimizer step per batch, so global_step counts them
        return every > 0 and ((self.global_step + 1) % every == 0 or bool(trainer.should_stop))

    @property
    def last_train_psnr(self) -> Tensor | None:
        """PSNR of the last training render, [] on the device (the progress bar copies it to the host when it
        refreshes, without waiting), or None before the first step."""
        return self._last_train_psnr

    def begin_stage2(self, step: int) -> None:
        """Stage 2 starts at `step`: the densifier's schedule (opacity resets) counts from here on."""
        self.densifier.restart_schedule(self.densifier_state, step)

    # ----------------------------------------------------------------------------------------------- divergence
    def _checkpoint_due(self, step: int) -> bool:
        """Whether a checkpoint is saved after the update that brings the count to `step` (train.py's periodic
        last.ckpt and the end of the run; no checkpoint is saved on validation)."""
        every = self.settings.callbacks.checkpoint_every
        return (every > 0 and step % every == 0) or step >= self.settings.trainer.max_steps

    def _deferred(self, optimizer: torch.optim.Optimizer) -> bool:
        """Whether this run's divergence probes are read after the step instead of before the update
        (`framework.lightning.deferred_checks`): `divergence.deferred` true, or auto on a GPU, with a fused Adam."""
        if self._defers_checks is None:
            want, fused = self.divergence.deferred, defers(optimizer)
            if want is True and not fused:
                raise ConfigError(
                    "divergence.deferred=true: the optimizer does not run fused Adam (float32 or float64 "
                    "parameters on a CPU or a CUDA GPU), so it cannot skip an update on the device. Set "
                    "divergence.deferred=auto."
                )
            on_gpu = any(p.is_cuda for g in optimizer.param_groups for p in g["params"])
            self._defers_checks = fused and (want is True or (want == "auto" and on_gpu))
        return self._defers_checks

    def _last_good_checkpoint(self) -> Path | None:
        trainer = self._trainer
        for callback in getattr(trainer, "checkpoint_callbacks", []) if trainer is not None else []:
            path = Path(str(callback.dirpath)) / "last.ckpt"
            if callback.dirpath and path.is_file():
                return path
        return None

    def _diverged(self, message: str, optimizer: torch.optim.Optimizer) -> None:
        """Stop with `message`, or roll back to the last good checkpoint with lower learning rates."""
        last = self._last_good_checkpoint()
        where = f"The last good checkpoint is {last}" if last else "No checkpoint was written before it"
        if self.divergence.action != "rollback" or last is None or self.rollbacks >= self.divergence.max_rollbacks:
            why = ""
            if self.divergence.action == "rollback":
                why = f" (no rollback: {'nothing to roll back to' if last is None else 'max_rollbacks reached'})"
            raise TrainingDiverged(
                f"{message}{why}. {where}; resume from it with lower learning rates (optim.lr.*), or set "
                f"divergence.action=rollback to recover automatically."
            )
        ckpt = torch.load(last, map_location=self.device, weights_only=False)
        rollbacks, lr_scale = self.rollbacks + 1, self.lr_scale * self.divergence.lr_factor
        self.on_load_checkpoint(ckpt)  # resizes the Gaussians, restores densifier state and stage
        self.load_state_dict(ckpt["state_dict"])
        optimizer.load_state_dict(ckpt["optimizer_states"][0])
        self.rollbacks, self.lr_scale = rollbacks, lr_scale
        stage1 = self.settings.stages.stage1_steps
        if 0 < stage1 and int(ckpt.get("global_step", 0)) < stage1 <= self.global_step:
            self.begin_stage2(stage1)  # the step count goes on: stage 2 began after that checkpoint was written
        print(
            f"[splatrig] {message}; rolled back to {last} (step {ckpt.get('global_step')}) with learning rates x"
            f"{self.lr_scale:g} (rollback {self.rollbacks} of {self.divergence.max_rollbacks})",
            file=sys.stderr,
        )

    def _densifier_optimizers(self, optimizer: torch.optim.Optimizer) -> dict[str, torch.optim.Optimizer]:
        """One optimizer serves every per-Gaussian key; the surgery finds each key's group by its name."""
        return {g["name"]: optimizer for g in optimizer.param_groups if g["name"] in GAUSSIAN_KEYS}

    def validation_step(self, batch: FrameBatch, batch_idx: int) -> None:
        out = self.render_batch(batch)
        value = psnr(out.render.rgb.clamp(0, 1), batch.image).mean()
        self.log("val/psnr", value, on_epoch=True, on_step=False, batch_size=1, prog_bar=True)

    @torch.no_grad()
    def bake_weights(self) -> bool:
        """Store the deformer's final blend weights in each Gaussian, so inference needs no weight field or MLP."""
        if self.avatar.body is None:
            return False
        if "skin_weights" in self.avatar.gaussians.params:
            return True  # already baked (a compact model has no F_dw left to bake again)
        weights = self.avatar.deformer.bake(self.avatar.gaussians.gaussians())
        if weights is None:
            return False
        self.avatar.gaussians.params["skin_weights"] = nn.Parameter(weights.detach().contiguous(), requires_grad=False)
        return True

    # -------------------------------------------------------------------------------------------- checkpointing
    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["densifier_state"] = {
            k: (v.detach().cpu() if isinstance(v, Tensor) else v) for k, v in self.densifier_state.items()
        }
        checkpoint["splatrig_stage"] = {
            "corrector_enabled": bool(self.avatar.corrector.enabled),
            "deformer_enabled": bool(self.avatar.deformer.enabled),
        }
        checkpoint["splatrig_divergence"] = {"lr_scale": self.lr_scale, "rollbacks": self.rollbacks}
        checkpoint["splatrig_rng"] = rng_states()

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        stored_cfg = checkpoint.get("hyper_parameters", {}).get("cfg")
        if stored_cfg is not None:
            _check_compatible(stored_cfg, self.cfg)
        self.avatar.gaussians.resize_to(checkpoint["state_dict"], "avatar.gaussians.")
        self._loaded_steps = int(checkpoint.get("global_step", 0))
        state = checkpoint.get("densifier_state")
        if state is not None:
            self.densifier_state = {k: (v.to(self.device) if isinstance(v, Tensor) else v) for k, v in state.items()}
        if "splatrig_rng" in checkpoint and self._trainer is not None:  # resuming: the model's random streams go on
            restore_rng_states(checkpoint["splatrig_rng"])
        divergence = checkpoint.get("splatrig_divergence", {})
        self.lr_scale = float(divergence.get("lr_scale", self.lr_scale))
        self.rollbacks = int(divergence.get("rollbacks", self.rollbacks))
        stage = checkpoint.get("splatrig_stage", {})
        if "corrector_enabled" in stage:
            self.avatar.corrector.enabled = stage["corrector_enabled"]
        if "deformer_enabled" in stage:
            self.avatar.deformer.enabled = stage["deformer_enabled"]


# The structural parts of a config a checkpoint depends on: change one and the stored tensors no longer fit.
STRUCTURAL_GROUPS = ("body", "corrector", "deformer", "data")


def rng_states() -> dict[str, Any]:
    """The global random streams (torch CPU and CUDA, numpy, python): densification draws from them."""
    import random

    import numpy as np

    states: dict[str, Any] = {"torch": torch.get_rng_state(), "numpy": np.random.get_state()}
    states["python"] = random.getstate()
    if torch.cuda.is_available():
        states["cuda"] = torch.cuda.get_rng_state_all()
    return states


def restore_rng_states(states: dict[str, Any]) -> None:
    import random

    import numpy as np

    torch.set_rng_state(states["torch"].cpu())
    np.random.set_state(states["numpy"])
    random.setstate(states["python"])
    if "cuda" in states and torch.cuda.is_available() and len(states["cuda"]) == torch.cuda.device_count():
        # RNG states are CPU byte tensors; a rollback loads its checkpoint onto the training device
        torch.cuda.set_rng_state_all([s.cpu() for s in states["cuda"]])


def _check_compatible(stored: dict[str, Any], current: dict[str, Any]) -> None:
    """The stored tensors fit this run's model only if its structural components are the same ones, built alike."""
    problems, fixes = [], []
    for group in STRUCTURAL_GROUPS:
        old_name, _ = node_kwargs(stored.get(group))
        new_name, _ = node_kwargs(current.get(group))
        if old_name != new_name:
            problems.append(f"{group}: checkpoint has '{old_name}', this run has '{new_name}'")
            fixes.append(f"{group}={old_name}")
    old_body, new_body = node_kwargs(stored.get("body"))[1], node_kwargs(current.get("body"))[1]
    if not problems and old_body != new_body:  # same body, another build of it (e.g. anny's skeleton)
        for k in sorted(k for k in set(old_body) | set(new_body) if old_body.get(k) != new_body.get(k)):
            problems.append(f"body.{k}: checkpoint has {old_body.get(k)!r}, this run has {new_body.get(k)!r}")
            fixes.append(f"body.{k}={old_body.get(k)}")
    if problems:
        raise ConfigError(
            "the checkpoint was made with an incompatible config (" + "; ".join(problems) + "). Resume with the "
            "checkpoint's choices (`" + " ".join(fixes) + "`), or start a new run without ckpt=."
        )


def _padded_box(points: Tensor, margin: float) -> Tensor:
    lo = points.min(0).values
    hi = points.max(0).values
    pad = (hi - lo) * margin
    return torch.stack([lo - pad, hi + pad])

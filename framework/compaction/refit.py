"""Refit a compacted avatar's Gaussians to the training images: prune, then a short fine-tune.

Why: pruning keeps the renders within a tolerance of the trained model's, so it can only remove Gaussians whose loss
the others already hide. A few hundred steps of the run's own loss afterwards let the remaining Gaussians take over
what the removed ones drew, so a model can be pruned much further at the same image quality (the prune-then-fine-tune
recipe of LightGaussian, Fan et al. 2023); measured in docs/results/scene_adaptive.md.

What moves: the Gaussians' own parameters (means, rotations, scales, opacities, SH), at the learning rates the run's
schedule ends with (`SplatModule._set_learning_rates` at its last step). What stays as trained: the networks (a kept
F_a, a partially folded F_a's rows), latent codes, the pose refiner and the skeleton; nothing densifies, and the SH
degree is the model's. Blend weights are whatever the avatar uses: stored ones stay fixed, and a caller that removes
rebuildable weights first (`framework.compaction.compact`) has them follow the means, as in training.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch
from tqdm.auto import tqdm

from framework.lightning.data import collate_frames

REFIT_KEYS = ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN")
"""The Gaussian parameters a refit optimises (not latents, which feed a kept F_a, nor baked blend weights)."""


@dataclass
class RefitResult:
    steps: int  # steps run (fewer than asked only when a non-finite loss stopped the refit)
    seconds: float
    loss_first: float  # mean total loss over the first tenth of the steps
    loss_last: float  # and over the last tenth
    stopped: str | None = None  # why the refit stopped early and restored the parameters it started from


def refit_gaussians(module, datamodule, steps: int, seed: int = 0, progress: bool = True) -> RefitResult:
    """Optimise the Gaussians of `module` (a `SplatModule`) for `steps` steps of its own loss on shuffled training
    frames (one image per step, as training); the module is left in eval mode. A non-finite loss restores the
    parameters the refit started from and stops it (`RefitResult.stopped`)."""
    if steps <= 0:
        return RefitResult(0, 0.0, math.nan, math.nan)
    params = module.avatar.gaussians.params
    keys = [k for k in REFIT_KEYS if k in params]
    start = {k: params[k].detach().clone() for k in keys}
    frozen = {p: p.requires_grad for p in module.parameters()}
    for p in module.parameters():
        p.requires_grad_(False)
    for k in keys:
        params[k].requires_grad_(True)
    groups = [{"params": [params[k]], "lr": 0.0, "name": k} for k in keys]
    optimizer = torch.optim.Adam(groups, eps=1e-15)
    module._set_learning_rates(optimizer, module.settings.trainer.max_steps)  # the schedule's end
    dataset = datamodule.train_set
    generator = torch.Generator().manual_seed(seed)
    device = params["means"].device
    losses: list[float] = []
    stopped = None
    module.train()
    t0 = time.perf_counter()
    order: list[int] = []
    bar = tqdm(range(steps), desc="refit", unit="step", disable=not progress, leave=False)
    try:
        for _ in bar:
            if not order:
                order = torch.randperm(len(dataset), generator=generator).tolist()
            batch = collate_frames([dataset[order.pop()]]).to(device)
            out = module.render_batch(batch)
            total, _ = module.loss_fn(out.render, batch, out.aux)
            loss = float(total.detach())  # the step's one host sync: shown by the bar; non-finite stops here
            if not math.isfinite(loss):
                stopped = f"non-finite loss ({loss}) at refit step {len(losses)}"
                break
            optimizer.zero_grad(set_to_none=True)
            total.backward()
            optimizer.step()
            losses.append(loss)
            bar.set_postfix(loss=f"{loss:.4f}", refresh=False)
    finally:
        bar.close()
        with torch.no_grad():
            if stopped is not None or not all(bool(torch.isfinite(params[k]).all()) for k in keys):
                stopped = stopped or "non-finite parameters after the refit"
                for k in keys:
                    params[k].copy_(start[k])
        for p, flag in frozen.items():
            p.requires_grad_(flag)
        module.eval()
    tenth = max(1, len(losses) // 10)
    first = sum(losses[:tenth]) / tenth if losses else math.nan
    last = sum(losses[-tenth:]) / tenth if losses else math.nan
    return RefitResult(len(losses), time.perf_counter() - t0, first, last, stopped)

"""3DGS adaptive density control (clone / split / prune / opacity reset) as the paper uses it.

Driven by the norm of the screen-space gradient of each Gaussian's projected mean, accumulated over the steps in which
it was visible. That gradient comes from the whole image loss: RGB and alpha terms are summed before one backward, so
`means2d.grad` already holds their sum. Decisions read only the canonical parameters in `params` (the scales and
opacities before the pose-dependent corrector), which are the ones densification edits.

Schedule (global training steps `step`):
  * refine (clone, split, prune) every `refine_every` steps for refine_start < step < refine_stop;
  * opacity reset, the paper's schedule: at `first_reset` (3000 in the paper, during stage 1), then every
    `reset_every` (6000) steps counted from the start T of stage 2 (T + 6000, T + 12000, ...). T is `reset_restart`
    when set (paper_full sets it from the profile's schedule, so a row that moves the stage switch, such as "w/o
    first stage", keeps the resets where they were); else the step the trainer's stage switch reports
    (`restart_schedule(state, T)`); a run with neither resets at first_reset, first_reset + reset_every, ...
    Resets belong to densification (as in 3DGS): none at or after refine_stop. Every milestone is a fraction of the
    run in the profile's `schedule:` (conf/profile/*.yaml);
  * after the first reset, Gaussians larger than `prune_scale3d * scene_scale` are pruned as well (3DGS).
Splits replace a Gaussian by `split_factor` samples drawn from it with scales / (0.8 * split_factor); clones copy it.
Growth never takes N above `max_gaussians` (the highest-gradient candidates win), which bounds CPU cost.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor, nn

from framework.geometry import quat_to_rotmat
from framework.interfaces.densifier import Densifier
from framework.model import optim_surgery as surgery
from framework.registry import register


@register("densifier", "paper")
class PaperDensifier(Densifier):
    def __init__(
        self,
        grad_threshold: float = 2e-4,
        refine_start: int = 500,
        refine_stop: int = 15_000,
        refine_every: int = 100,
        reset_every: int = 6000,
        first_reset: int = 3000,
        prune_opacity: float = 0.005,
        reset_opacity: float = 0.01,
        grow_scale3d: float = 0.01,
        prune_scale3d: float = 0.1,
        max_gaussians: int | None = None,
        split_factor: int = 2,
        verbose: bool = False,
        reset_restart: int | None = None,
    ) -> None:
        if refine_every <= 0 or reset_every <= 0:
            raise ValueError(
                f"densifier 'paper': refine_every ({refine_every}) and reset_every ({reset_every}) must be positive."
            )
        if split_factor < 2:
            raise ValueError(f"densifier 'paper': split_factor must be >= 2, got {split_factor}.")
        if reset_restart is not None and reset_restart < 0:
            raise ValueError(f"densifier 'paper': reset_restart must be >= 0 or null, got {reset_restart}.")
        if not 0.0 < reset_opacity < 1.0:
            raise ValueError(f"densifier 'paper': reset_opacity must be in (0, 1), got {reset_opacity}.")
        self.grad_threshold = grad_threshold
        self.refine_start = refine_start
        self.refine_stop = refine_stop
        self.refine_every = refine_every
        self.reset_every = reset_every
        self.first_reset = first_reset
        self.reset_restart = reset_restart
        self.prune_opacity = prune_opacity
        self.reset_opacity = reset_opacity
        self.grow_scale3d = grow_scale3d
        self.prune_scale3d = prune_scale3d
        self.max_gaussians = max_gaussians if max_gaussians and max_gaussians > 0 else None
        self.split_factor = split_factor
        self.verbose = verbose

    # -- protocol ---------------------------------------------------------------------------------------------------

    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        # grad2d / count are created lazily on the first step, on the parameters' device.
        return {
            "grad2d": None,
            "count": None,
            "scene_scale": float(scene_scale),
            "stage2_start": None,  # set by restart_schedule when stage 2 begins
            "last": {},
        }

    def restart_schedule(self, state: dict[str, Any], step: int) -> None:
        """Stage 2 begins at `step`: from here on, resets come every `reset_every` steps counted from it (unless
        `reset_restart` fixes that step in the config)."""
        state["stage2_start"] = int(step)

    def step_pre_backward(self, params, optimizers, state, step, info) -> None:
        means2d = info.get("means2d")
        if isinstance(means2d, Tensor) and means2d.requires_grad and not means2d.is_leaf:
            means2d.retain_grad()

    @torch.no_grad()
    def step_post_backward(self, params, optimizers, state, step, info) -> None:
        state["last"] = {}
        if step >= self.refine_stop:
            return
        self.accumulate(params, state, info)
        if step > self.refine_start and step % self.refine_every == 0:
            n_clone, n_split = self.grow(params, optimizers, state)
            n_prune = self.prune(params, optimizers, state, step)
            state["grad2d"].zero_()
            state["count"].zero_()
            state["last"].update(clone=n_clone, split=n_split, prune=n_prune)
            if self.verbose:
                print(
                    f"step {step}: +{n_clone} cloned, +{n_split} split, -{n_prune} pruned -> "
                    f"{params['means'].shape[0]} Gaussians"
                )
        if self.is_reset_step(step, state):
            self.reset_opacity_(params, optimizers)
            state["last"]["reset"] = True

    # -- pieces -----------------------------------------------------------------------------------------------------

    def is_reset_step(self, step: int, state: dict[str, Any]) -> bool:
        if step >= self.refine_stop:
            return False
        start = self.reset_restart if self.reset_restart is not None else state.get("stage2_start")
        if start is not None and step >= start:
            return step > start and (step - start) % self.reset_every == 0
        return step >= self.first_reset and (step - self.first_reset) % self.reset_every == 0

    def accumulate(self, params: dict[str, nn.Parameter], state: dict[str, Any], info: dict[str, Any]) -> None:
        """Add |d loss / d means2d| in NDC units for every Gaussian visible in a camera, and count the views."""
        n = _check_params(params)
        device = params["means"].device
        if state["grad2d"] is None or state["grad2d"].shape[0] != n:
            state["grad2d"] = torch.zeros(n, device=device)
            state["count"] = torch.zeros(n, device=device)
        elif state["grad2d"].device != device:  # restored from a checkpoint before Lightning moved the module
            state["grad2d"], state["count"] = state["grad2d"].to(device), state["count"].to(device)
        means2d = info.get("means2d")
        grad = getattr(means2d, "grad", None)
        if grad is None or n == 0:
            return
        grad = grad.detach().clone().float()  # [C, N, 2]
        if grad.dim() == 2:
            grad = grad.unsqueeze(0)
        if grad.shape[1] != n:
            raise ValueError(
                f"densifier 'paper': info['means2d'] has {grad.shape[1]} Gaussians, params have {n}; "
                f"pass the means2d of the render of exactly these Gaussians."
            )
        n_cams = int(info.get("n_cameras", grad.shape[0]))
        grad[..., 0] *= info["width"] / 2.0 * n_cams  # pixels -> NDC, and undo the mean over cameras (gsplat)
        grad[..., 1] *= info["height"] / 2.0 * n_cams
        radii = info["radii"]
        visible = (radii > 0).all(dim=-1) if radii.dim() == 3 else radii > 0  # [C, N]
        # Masked sums over the cameras rather than indexing the visible pairs: no data-dependent shape, so no host
        # sync on a GPU (boolean indexing waits for the count). Culled rows add an exact 0 (`where`, not a product, so
        # a non-finite gradient in a row gsplat never wrote cannot leak in).
        norms = torch.where(visible, grad.norm(dim=-1), 0.0)  # [C, N]
        state["grad2d"] += norms.sum(0)
        state["count"] += visible.sum(0, dtype=state["count"].dtype)

    def grow(self, params: dict[str, nn.Parameter], optimizers, state: dict[str, Any]) -> tuple[int, int]:
        n = params["means"].shape[0]
        if n == 0:
            return 0, 0
        avg = state["grad2d"] / state["count"].clamp_min(1)  # [N]
        high = avg >= self.grad_threshold
        big = params["log_scales"].exp().amax(dim=-1) > self.grow_scale3d * state["scene_scale"]  # [N]
        clone, split = high & ~big, high & big
        if self.max_gaussians is not None:
            clone, split = self._cap(avg, clone, split, self.max_gaussians - n)
        n_clone, n_split = int(clone.sum()), int(split.sum())
        if n_clone:
            self.clone(params, optimizers, state, clone)
            split = torch.cat([split, split.new_zeros(n_clone)])  # fresh clones are not split
        if n_split:
            self.split(params, optimizers, state, split)
        return n_clone, n_split

    def _cap(self, score: Tensor, clone: Tensor, split: Tensor, budget: int) -> tuple[Tensor, Tensor]:
        """Keep the highest-gradient candidates whose growth (+1 per clone, +split_factor-1 per split) fits."""
        cand = torch.nonzero(clone | split, as_tuple=True)[0]
        cost = torch.where(split[cand], self.split_factor - 1, 1)
        order = torch.argsort(score[cand], descending=True, stable=True)
        fits = torch.cumsum(cost[order], 0) <= max(budget, 0)
        chosen = torch.zeros_like(clone)
        chosen[cand[order][fits]] = True
        return clone & chosen, split & chosen

    def clone(self, params, optimizers, state: dict[str, Any], mask: Tensor) -> None:
        """Copy the selected Gaussians (same position, new rows with zero optimizer state)."""
        sel = torch.nonzero(mask, as_tuple=True)[0]
        surgery.append_rows(params, optimizers, {k: p.detach()[sel] for k, p in params.items()})
        self._extend_state(state, sel)

    def split(self, params, optimizers, state: dict[str, Any], mask: Tensor) -> None:
        """Replace each selected Gaussian by `split_factor` samples from it, scales shrunk by 0.8 * split_factor."""
        k = self.split_factor
        sel = torch.nonzero(mask, as_tuple=True)[0]
        rest = torch.nonzero(~mask, as_tuple=True)[0]
        means, log_scales, quats = params["means"].detach(), params["log_scales"].detach(), params["quats"].detach()
        scales = log_scales[sel].exp()  # [S, 3]
        R = quat_to_rotmat(quats[sel], self.execution)  # [S, 3, 3]
        noise = torch.randn(k, sel.numel(), 3, device=means.device, dtype=means.dtype)
        offsets = torch.einsum("sij,sj,ksj->ksi", R, scales, noise)  # [k, S, 3]
        new = {}
        for name, p in params.items():
            p = p.detach()
            if name == "means":
                new[name] = (p[sel].unsqueeze(0) + offsets).reshape(-1, 3)
            elif name == "log_scales":
                new[name] = (p[sel] - math.log(0.8 * k)).repeat(k, 1)
            else:
                new[name] = p[sel].repeat(k, *([1] * (p.dim() - 1)))
        surgery.keep_rows(params, optimizers, rest)
        surgery.append_rows(params, optimizers, new)
        for key in ("grad2d", "count"):
            if state.get(key) is not None:
                v = state[key]
                state[key] = torch.cat([v[rest], v[sel].repeat(k)])

    def prune(self, params, optimizers, state: dict[str, Any], step: int) -> int:
        if params["means"].shape[0] == 0:
            return 0
        remove = params["opacity_logits"].detach().reshape(-1).sigmoid() < self.prune_opacity
        if step > self.first_reset:
            remove |= params["log_scales"].detach().exp().amax(dim=-1) > self.prune_scale3d * state["scene_scale"]
        n = int(remove.sum())
        if n:
            keep = torch.nonzero(~remove, as_tuple=True)[0]
            surgery.keep_rows(params, optimizers, keep)
            for key in ("grad2d", "count"):
                if state.get(key) is not None:
                    state[key] = state[key][keep]
        return n

    def reset_opacity_(self, params, optimizers) -> None:
        """Clamp opacities to at most `reset_opacity` (3DGS: 0.01); Adam moments of the opacity restart at zero."""
        limit = math.log(self.reset_opacity / (1.0 - self.reset_opacity))
        values = params["opacity_logits"].detach().clamp(max=limit)
        surgery.replace_values(params, optimizers, "opacity_logits", values)

    @staticmethod
    def _extend_state(state: dict[str, Any], sel: Tensor) -> None:
        for key in ("grad2d", "count"):
            if state.get(key) is not None:
                state[key] = torch.cat([state[key], state[key][sel]])


REQUIRED = ("means", "quats", "log_scales", "opacity_logits")


def _check_params(params: dict[str, nn.Parameter]) -> int:
    missing = [k for k in REQUIRED if k not in params]
    if missing:
        raise ValueError(
            f"densifier 'paper': params lack {missing}; it needs the canonical {list(REQUIRED)} "
            f"(plus every other per-Gaussian parameter, so that all of them follow N)."
        )
    return surgery.num_rows(params)

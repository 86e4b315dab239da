"""Compact a trained avatar for inference: learned pruning (`framework.compaction.pruning`), F_dw baked into
per-Gaussian weights, training-only state dropped; with a before/after report (Gaussians, size, render speed, PSNR).

`prune_checkpoint(ckpt, out)` writes a checkpoint every entry point loads as usual (evaluate, render,
tools/bench_render.py): the config stored in it is updated to what the compact model is (SH degree, `deformer=lbs`
once F_dw is baked), and the optimizer state, which only resuming needs, is left out.

Measurements, as tools/bench_render.py takes them (`framework.evaluation.frame_timing`): novel-pose fps renders a new
pose every frame (F_a, LBS with baked weights, rasterisation) from the novel-pose split's frames and cameras; novel-view
fps renders one pose from changing cameras (posed Gaussians cached). PSNR is over whole images of each split.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

from framework.atomic import atomic_path
from framework.compaction.corrector_fold import DEFAULT_FOLD_TOLERANCE, CorrectorFold, fold_corrector, fold_outcome
from framework.compaction.pruning import (
    DEFAULT_MIN_WEIGHT,
    DEFAULT_SH_TOLERANCE,
    contributions,
    drop_sh_bands,
    negligible_sh_degree,
    prune_gaussians,
    prune_within_tolerance,
    sh_band_rms,
)
from framework.compaction.refit import RefitResult, refit_gaussians
from framework.compaction.render_check import RenderCheck
from framework.config_schema import Train
from framework.errors import SplatrigError
from framework.evaluation.run_cost import distinct_frame_items, model_bytes, render_fps, timing_split
from framework.lightning.data import collate_frames
from framework.lightning.trained_model import datamodule_for, interleaved_fps, load_module
from framework.paths import DEMO, beside_checkpoint, checkpoint_file
from framework.runtime import default_device
from framework.scene.auto import group_option

CHECK_FRAMES = 12  # training frames (one view each) every image-checked compaction step renders
DEFAULT_REFIT_STEPS = 1500
"""Steps of the refit after pruning (`framework.compaction.refit`): long enough that the pruned models of the studio
scenes stay within the 0.3 dB budget (docs/results/scene_adaptive.md). `conf/prune.yaml` and `conf/export.yaml`
repeat it."""
DEFAULT_PRUNE_TOLERANCE = 0.03
"""RMS colour (over the avatar's pixels of the checked training frames) that pruning may reach when the refit
follows: the refit recovers what a deeper prune loses, so it prunes further than `NO_REFIT_PRUNE_TOLERANCE`
(measured trade: docs/results/scene_adaptive.md)."""
NO_REFIT_PRUNE_TOLERANCE = 0.7 * DEFAULT_FOLD_TOLERANCE
"""The tolerance `"auto"` means with `refit_steps=0`: nothing repairs what pruning changes, so it stays small, and the
rest of the fold tolerance is left to a partial F_a fold, checked against the same original renders."""


def resolve_prune_tolerance(tolerance: float | str | None, refit_steps: int) -> float | None:
    """`"auto"`: `DEFAULT_PRUNE_TOLERANCE` when a refit follows, else `NO_REFIT_PRUNE_TOLERANCE`; a number as given;
    None (no faint-Gaussian pruning) as None."""
    if tolerance == "auto":
        return DEFAULT_PRUNE_TOLERANCE if refit_steps > 0 else NO_REFIT_PRUNE_TOLERANCE
    return None if tolerance is None else float(tolerance)


def resolve_fold_tolerance(tolerance: float | str | None, settings: Train) -> tuple[float | None, str | None]:
    """(tolerance, why F_a is kept whole or None). `"auto"`: `DEFAULT_FOLD_TOLERANCE`, or None (no fold) when the run
    was trained with `scene.fold_corrector: false` (`+scene=auto` sets it where the scene's appearance depends on
    the pose, `framework.scene.auto`); a number as given; None as None. A run from before the key folds."""
    if tolerance != "auto":
        return (None if tolerance is None else float(tolerance)), None
    if settings.scene.fold_corrector:
        return DEFAULT_FOLD_TOLERANCE, None
    return None, (
        "the run's scene.fold_corrector is false (`+scene=auto` measured pose-dependent appearance)"
        f"; fold_tolerance={DEFAULT_FOLD_TOLERANCE:.3g} folds it anyway"
    )


@dataclass
class ModelMeasure:
    """Size, speed and quality of one model."""

    num_gaussians: int
    sh_degree: int
    model_bytes: int  # learned tensors (the body's mesh, rebuilt from its config, is not counted)
    file_bytes: int | None
    novel_pose_fps: float | None
    novel_view_fps: float | None
    psnr: dict[str, float] = field(default_factory=dict)


@dataclass
class PruneReport:
    ckpt: str
    out: str
    before: ModelMeasure
    after: ModelMeasure
    removed_gaussians: int
    min_weight: float
    sh_band_rms: list[float]
    sh_tolerance: float
    weights_baked: bool
    device: str
    corrector_fold: dict[str, Any] | None = None  # CorrectorFold as a dict: spread per attribute, tolerance, folded
    prune_tolerance: float | None = None  # faint Gaussians removed while the checked frames stay within it
    removed_within_tolerance: int = 0  # of removed_gaussians, those beyond the min_weight threshold
    render_rms: float | None = None  # the compact model's checked training frames against the original's
    skin_weights_stored: bool | None = True  # False: the body's field at the means, rebuilt on loading; None: no body
    refit: dict[str, Any] | None = None  # RefitResult as a dict when the Gaussians were refitted after pruning
    corrector_kept: str | None = None  # why F_a was kept whole without a fold being tried (`resolve_fold_tolerance`)
    prune_rounds: int = 1  # pruning and refit rounds (`prune_checkpoint`'s prune_rounds)
    timing_rasterizer: str | None = None  # the backend the frame rates were timed with; None: the model's own

    def summary(self) -> str:
        """The before/after table and what was removed, baked and folded, as printed by prune and export."""
        faint = (
            (
                f", {self.removed_within_tolerance} of them by the smallest mean squared blending weight per covered "
                f"pixel while the training frames stayed within "
                f"{self.prune_tolerance:.4g} RMS"
            )
            if self.prune_tolerance is not None
            else ""
        )
        lines = [
            f"\n{self.table()}\n",
            f"[splatrig] removed {self.removed_gaussians} Gaussians (max blending weight "
            f"< {self.min_weight:.4g}{faint}); "
            f"SH band RMS {[round(x, 5) for x in self.sh_band_rms]}; "
            f"F_dw {'baked' if self.weights_baked else 'absent'}; "
            f"{skin_weights_outcome(self.skin_weights_stored)}; "
            f"device {self.device}",
        ]
        if self.corrector_fold is not None:
            f = self.corrector_fold
            spread = ", ".join(f"{k} {v:.4f}" for k, v in f["spread"].items())
            lines.append(
                f"[splatrig] F_a {fold_outcome(f)}: training frames render {f['render_rms']:.5f} RMS apart "
                f"(fold_tolerance {f['tolerance']:.4g}); "
                f"largest spread of its output over the training poses: {spread}"
            )
        if self.corrector_kept:
            lines.append(f"[splatrig] F_a kept whole: {self.corrector_kept}")
        if self.render_rms is not None:
            before_refit = " before the refit" if self.refit else ""
            lines.append(
                f"[splatrig] the compact model renders the checked training frames {self.render_rms:.5f} "
                f"RMS (over the avatar's pixels) from the original{before_refit}"
            )
        if self.refit:
            r = self.refit
            rounds = f" in {self.prune_rounds} rounds of pruning and refit" if self.prune_rounds > 1 else ""
            lines.append(
                f"[splatrig] refit the remaining Gaussians for {r['steps']} steps{rounds} "
                f"({r['seconds']:.0f} s): training loss {r['loss_first']:.5f} -> {r['loss_last']:.5f}"
                + (f"; stopped: {r['stopped']}, parameters restored" if r["stopped"] else "")
            )
        lines.append(f"[splatrig] compact model: {self.out}")
        return "\n".join(lines)

    def table(self) -> str:
        from framework.plugins import format_table

        def ratio(a: float | None, b: float | None, inverse: bool = False) -> str:
            if not a or not b:
                return "-"
            return f"{(a / b if inverse else b / a):.2f}x"

        b, a = self.before, self.after
        rows = [
            ("Gaussians", str(b.num_gaussians), str(a.num_gaussians), ratio(b.num_gaussians, a.num_gaussians, True)),
            ("SH degree", str(b.sh_degree), str(a.sh_degree), ""),
            (
                "model (learned) MiB",
                f"{b.model_bytes / 2**20:.2f}",
                f"{a.model_bytes / 2**20:.2f}",
                ratio(b.model_bytes, a.model_bytes, True),
            ),
            ("checkpoint file MiB", _mib(b.file_bytes), _mib(a.file_bytes), ratio(b.file_bytes, a.file_bytes, True)),
            (
                f"novel-pose fps{self._timed_with()}",
                _num(b.novel_pose_fps),
                _num(a.novel_pose_fps),
                ratio(b.novel_pose_fps, a.novel_pose_fps),
            ),
            (
                f"novel-view fps{self._timed_with()}",
                _num(b.novel_view_fps),
                _num(a.novel_view_fps),
                ratio(b.novel_view_fps, a.novel_view_fps),
            ),
        ]
        for split in b.psnr:
            pb, pa = b.psnr[split], a.psnr.get(split)
            rows.append((f"{split} PSNR dB", f"{pb:.3f}", _num(pa, 3), "-" if pa is None else f"{pa - pb:+.3f}"))
        return format_table(rows, ("", "before", "after", "change"))

    def _timed_with(self) -> str:
        return f" ({self.timing_rasterizer})" if self.timing_rasterizer else ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def skin_weights_outcome(stored: bool | None) -> str:
    """How a compact model carries its blend weights, in words (for `PruneReport.skin_weights_stored`)."""
    if stored is None:
        return "no skin weights (no body)"
    return "skin weights stored" if stored else "skin weights rebuilt from the body on loading"


def _mib(n: int | None) -> str:
    return "-" if n is None else f"{n / 2**20:.2f}"


def _num(x: float | None, digits: int = 1) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


# ------------------------------------------------------------------------------------------------- measuring
@torch.no_grad()
def measure_module(
    module,
    dm,
    splits: tuple[str, ...] = ("novel_view", "novel_pose"),
    warmup: int = 3,
    repeats: int = 10,
    file_bytes: int | None = None,
) -> ModelMeasure:
    """Gaussian count, learned size, novel-pose / novel-view fps (bench_render's rules) and PSNR per split."""
    from framework.plugins import load_plugins
    from framework.registry import METRICS

    load_plugins()
    module.eval()
    size = model_bytes(module)  # as stored: weights a compact model rebuilds on loading are not counted
    module.bake_weights()  # as tools/bench_render.py: the real-time path uses baked weights
    device = module.device
    psnr_metric = METRICS.build("psnr")
    psnr: dict[str, float] = {}
    for split in splits:
        try:
            dataset = dm.split(split)
        except SplatrigError:
            continue
        values = []
        for i in range(len(dataset)):
            batch = collate_frames([dataset[i]]).to(device)
            rgb = module.render_batch(batch).render.rgb.clamp(0, 1)
            values.append(float(psnr_metric(rgb, batch.image)[0]))
        psnr[split] = sum(values) / max(len(values), 1)
    pose_fps = view_fps = None
    split = "novel_pose" if "novel_pose" in psnr else next(iter(psnr), None)
    if split is not None and repeats > 0:
        pose_fps, view_fps = render_fps(module, dm, split, warmup=warmup, repeats=repeats)
    return ModelMeasure(
        num_gaussians=module.avatar.gaussians.num,
        sh_degree=module.sh_degree(module.trained_steps()),
        model_bytes=size,
        file_bytes=file_bytes,
        novel_pose_fps=pose_fps,
        novel_view_fps=view_fps,
        psnr=psnr,
    )


# ------------------------------------------------------------------------------------------------- compacting
def bake_weight_residual(module) -> bool:
    """Store the final blend weights per Gaussian and drop what only computed them (`Deformer.release_after_bake`:
    F_dw, and the stored config becomes `deformer=lbs`)."""
    if not module.bake_weights():
        return False
    replacement = module.avatar.deformer.release_after_bake()
    if replacement is not None:
        module.cfg["deformer"] = group_option("deformer", replacement, module.cfg["deformer"])
    return True


def check_batches(module, dm, max_frames: int = CHECK_FRAMES) -> list:
    """The training frames (one view each, spread over the split) that image-checked compaction steps render."""
    dataset = dm.train_set
    return [collate_frames([dataset[i]]).to(module.device) for i in distinct_frame_items(dataset, max_frames)]


def has_pose_corrector(avatar) -> bool:
    """Whether the avatar has a learned pose-driven corrector (something a fold could remove)."""
    return avatar.body is not None and any(True for _ in avatar.corrector.parameters())


def fold_module_corrector(
    module,
    dm,
    tolerance: float = DEFAULT_FOLD_TOLERANCE,
    max_frames: int = CHECK_FRAMES,
    check: RenderCheck | None = None,
    partial: bool = False,
) -> CorrectorFold | None:
    """Fold F_a into the Gaussians when the training frames render the same without it (`framework.model.
    corrector_fold`; with `partial`, as much of it as they allow); the stored config becomes `corrector=none` when
    all of it went. None when there is no pose-driven corrector."""
    avatar = module.avatar
    if not has_pose_corrector(avatar):
        return None
    batches = check.batches if check is not None else check_batches(module, dm, max_frames)
    sh_degree = check.sh_degree if check is not None else module.sh_degree(module.trained_steps())
    fold = fold_corrector(avatar, batches, sh_degree, tolerance, check=check, partial=partial)
    if fold.folded:
        module.cfg["corrector"] = group_option("corrector", "none", module.cfg["corrector"])
    return fold


@torch.no_grad()
def prune_module(
    module,
    dm,
    min_weight: float = DEFAULT_MIN_WEIGHT,
    sh_tolerance: float = DEFAULT_SH_TOLERANCE,
    max_frames: int | None = None,
    check: RenderCheck | None = None,
    tolerance: float | None = None,
) -> tuple[int, int, list[float]]:
    """Remove Gaussians whose blending weight never reaches `min_weight` over the training views and poses; with a
    `check` and `tolerance`, then others, the smallest mean squared blending weight per covered pixel first
    (`framework.compaction.pruning`), while the checked frames stay within it; then the SH bands whose RMS colour change
    is below `sh_tolerance`. Returns (Gaussians removed, of them within the tolerance, band RMS)."""
    dataset = dm.train_set
    frames = sorted({dataset.sample(i)[0] for i in range(len(dataset))})
    if max_frames and frames and len(frames) > max_frames:
        keep = {frames[int(round(k))] for k in torch.linspace(0, len(frames) - 1, max_frames).tolist()}
    else:
        keep = None

    def batches():
        for i in range(len(dataset)):
            if keep is not None and dataset.sample(i)[0] not in keep:
                continue
            yield collate_frames([dataset[i]]).to(module.device)

    avatar = module.avatar
    seen = contributions(avatar, batches())
    visible = seen.max >= min_weight
    removed = prune_gaussians(avatar.gaussians, visible, avatar.corrector)
    faint = 0
    if check is not None and tolerance is not None:
        faint = prune_within_tolerance(avatar, check, seen.mean_square[visible], tolerance)
    params = avatar.gaussians
    rms = sh_band_rms(params.params["shN"])
    corrector_cfg = module.cfg.get("corrector") or {}
    floor = int(corrector_cfg.get("sh_degree", 3)) if corrector_cfg.get("all_sh") else 0
    current = module.sh_degree(module.trained_steps())  # bands above it are stored but never rendered
    degree = min(negligible_sh_degree(params.params["shN"], sh_tolerance, floor=floor), current)
    if degree < current:
        drop_sh_bands(params, degree)
        module.set_sh_degree(degree)
        if check is not None:
            check.sh_degree = degree
    return removed + faint, faint, rms


def rebuildable_skin_weights(module) -> bool:
    """True when the stored blend weights are the body's weight field at the canonical means (no F_dw residual in
    them), so a loaded model rebuilds them exactly (`deformer=lbs` binds the field; `bake_weights` samples it)."""
    params = module.avatar.gaussians.params
    if "skin_weights" not in params:
        return False
    return module.avatar.deformer.rebuilds_weights(params["means"].detach(), params["skin_weights"].detach())


def write_compact_checkpoint(module, source: dict[str, Any], out_path: Path, skin_weights: bool = True) -> None:
    """The module as a checkpoint for inference: weights, updated config, step count; no optimizer state. Without
    `skin_weights`, the baked blend weights are left out (only when `rebuildable_skin_weights`)."""
    state = {k: v.detach().cpu() for k, v in module.state_dict().items()}
    if not skin_weights:
        state.pop("avatar.gaussians.params.skin_weights", None)
    hparams = dict(source.get("hyper_parameters", {}))
    hparams["cfg"] = module.cfg
    kept = ("epoch", "global_step", "pytorch-lightning_version", "hparams_name")
    ckpt = {key: source[key] for key in kept if key in source}
    ckpt.update(
        state_dict=state,
        hyper_parameters=hparams,
        densifier_state={},
        splatrig_stage=source.get("splatrig_stage", {}),
    )
    with atomic_path(out_path) as tmp:
        torch.save(ckpt, tmp)


def prune_checkpoint(
    ckpt_path: str | Path,
    out_path: str | Path | None = None,
    *,
    min_weight: float = DEFAULT_MIN_WEIGHT,
    sh_tolerance: float = DEFAULT_SH_TOLERANCE,
    max_frames: int | None = None,
    measure: bool = True,
    warmup: int = 3,
    repeats: int = 10,
    device: str | None = None,
    fold_tolerance: float | str | None = "auto",
    prune_tolerance: float | str | None = "auto",
    refit_steps: int = DEFAULT_REFIT_STEPS,
    rounds: int = 5,
    prune_rounds: int = 1,
    timing_rasterizer: str | None = None,
) -> PruneReport:
    """Prune, bake and write `ckpt_path` as a compact checkpoint (default: `<name>.pruned.ckpt` beside it) and
    measure the model before and after (the written file is loaded back for the "after" numbers; frame rates: both
    files timed interleaved, `rounds` rounds of `repeats` frames, `framework.lightning.trained_model.interleaved_fps`).

    In order, each image-checked step measured against the original renders of `CHECK_FRAMES` training frames:
    F_dw baked; F_a folded whole when the frames render within `fold_tolerance` without it (`"auto"`: 1/255, or no
    fold where the run's scene survey asked to keep F_a whole, `resolve_fold_tolerance`); Gaussians that never
    reach `min_weight` removed, then others (the smallest mean squared blending weight per covered pixel first)
    while the frames stay within `prune_tolerance` (`"auto"`: 0.03 with a refit, 0.7/255 without,
    `resolve_prune_tolerance`); negligible SH bands dropped; then, if F_a was kept, folded for as many Gaussians as
    keep the frames within `fold_tolerance` (of the original renders; with a refit, of the pruned model's, since the
    refit repairs both steps); then, with `refit_steps`, the remaining Gaussians refitted to the training images
    (`framework.compaction.refit`; blend weights that are the body's field at the means follow the means, as in
    training, and are baked again after).
    With `prune_rounds` > 1 and a refit, pruning and the refit then repeat: each later round prunes within the same
    tolerances of the refitted model's renders and refits `refit_steps` steps again, so the refits take
    `prune_rounds * refit_steps` steps in all.
    None for a tolerance skips its step. Blend weights the body's field reproduces are not stored.
    `timing_rasterizer` renders the timed frames of both models with that backend (e.g. `numba`, the compiled CPU
    frame); None: the one the model trained with. PSNR and the compaction's own checks always use the model's."""
    if prune_rounds < 1:
        raise SplatrigError(f"prune_rounds={prune_rounds}: expected 1 or more (1: prune once, then refit).")
    prune_tolerance = resolve_prune_tolerance(prune_tolerance, refit_steps)
    shipped = str(ckpt_path) == DEMO  # the packaged demo: its compact copy goes to outputs/, not into the package
    ckpt_path = checkpoint_file(ckpt_path)
    default_out = beside_checkpoint(DEMO, "prune") if shipped else ckpt_path.parent
    out = Path(out_path) if out_path else default_out / f"{ckpt_path.stem}.pruned.ckpt"
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.resolve() == ckpt_path.resolve():
        raise SplatrigError(f"out={out}: the compact model must not overwrite its source checkpoint; choose another.")
    device = device or default_device()
    module = load_module(ckpt_path, device)
    fold_tolerance, corrector_kept = resolve_fold_tolerance(fold_tolerance, module.settings)
    dm = datamodule_for(module)
    source = torch.load(ckpt_path, map_location="cpu", weights_only=False)
    before = (
        measure_module(module, dm, repeats=0, file_bytes=ckpt_path.stat().st_size)
        if measure
        else _size_only(module, ckpt_path.stat().st_size)
    )
    module.bake_weights()
    baked = bake_weight_residual(module)
    check = RenderCheck.of(module.avatar, check_batches(module, dm), module.sh_degree(module.trained_steps()))
    fold = None if fold_tolerance is None else fold_module_corrector(module, dm, fold_tolerance, check=check)
    removed, faint, rms = prune_module(
        module, dm, min_weight, sh_tolerance, max_frames, check=check, tolerance=prune_tolerance
    )  # on the folded model
    if fold is not None and not fold.folded:
        # Without a refit, pruning and the partial fold share the fold tolerance from the original renders. With one,
        # the refit repairs what both changed, so the fold gets its own budget, measured from the pruned model.
        fold_check = RenderCheck.of(module.avatar, check.batches, check.sh_degree) if refit_steps > 0 else check
        fold = fold_module_corrector(module, dm, fold_tolerance, check=fold_check, partial=True)
    render_rms = check.rms(module.avatar)
    refit = None
    for round_index in range(prune_rounds if refit_steps > 0 else 1):
        if round_index:  # a later round: the refitted model is the new reference, pruned within the same tolerance
            more, more_faint = prune_again(
                module, dm, min_weight, max_frames, prune_tolerance, check.batches, check.sh_degree
            )
            removed, faint = removed + more, faint + more_faint
        if refit_steps > 0:
            refit = merge_refits(refit, refit_module(module, dm, refit_steps))
    skin_weights = not rebuildable_skin_weights(module)
    write_compact_checkpoint(module, source, out, skin_weights=skin_weights)
    has_weights = "skin_weights" in module.avatar.gaussians.params  # a static scene's Gaussians have none
    compact = load_module(out, device)
    after = (
        measure_module(compact, dm, repeats=0, file_bytes=out.stat().st_size)
        if measure
        else _size_only(compact, out.stat().st_size)
    )
    if measure and repeats > 0 and rounds > 0 and timing_split(dm) is not None:  # no held-out split: no frame rates
        fps = interleaved_fps(
            {"before": ckpt_path, "after": out}, warmup, repeats, rounds, str(device), timing_rasterizer
        )
        before.novel_pose_fps, before.novel_view_fps = fps["before"]
        after.novel_pose_fps, after.novel_view_fps = fps["after"]
    return PruneReport(
        str(ckpt_path),
        str(out),
        before,
        after,
        removed,
        float(min_weight),
        rms,
        float(sh_tolerance),
        baked,
        str(device),
        None if fold is None else asdict(fold),
        None if prune_tolerance is None else float(prune_tolerance),
        faint,
        render_rms,
        skin_weights if has_weights else None,
        None if refit is None else asdict(refit),
        corrector_kept if has_pose_corrector(compact.avatar) else None,
        prune_rounds if refit_steps > 0 else 1,
        timing_rasterizer,
    )


def refit_module(module, dm, steps: int) -> RefitResult:
    """Refit the Gaussians (`framework.compaction.refit`); blend weights that are the body's field at the means follow
    the means during the refit, as in training, and are baked again after."""
    if rebuildable_skin_weights(module):
        del module.avatar.gaussians.params["skin_weights"]
    result = refit_gaussians(module, dm, steps)
    module.bake_weights()
    return result


def merge_refits(first: RefitResult | None, then: RefitResult) -> RefitResult:
    """One report for refits run one after the other: steps and seconds add up, the losses span them all."""
    if first is None:
        return then
    return RefitResult(
        first.steps + then.steps,
        first.seconds + then.seconds,
        first.loss_first,
        then.loss_last,
        first.stopped or then.stopped,
    )


@torch.no_grad()
def prune_again(
    module, dm, min_weight: float, max_frames: int | None, tolerance: float | None, batches, sh_degree: int
) -> tuple[int, int]:
    """Another pruning round after a refit (`prune_rounds`): the same thresholds, measured from the refitted model's
    own renders, since the refit moved the Gaussians the last round's reference was drawn with. Returns (Gaussians
    removed, of them within the tolerance)."""
    check = RenderCheck.of(module.avatar, batches, sh_degree)
    removed, faint, _ = prune_module(
        module, dm, min_weight, sh_tolerance=0.0, max_frames=max_frames, check=check, tolerance=tolerance
    )  # SH bands were settled in the first round
    return removed, faint


def _size_only(module, file_bytes: int) -> ModelMeasure:
    return ModelMeasure(
        module.avatar.gaussians.num,
        module.sh_degree(module.trained_steps()),
        model_bytes(module),
        file_bytes,
        None,
        None,
    )

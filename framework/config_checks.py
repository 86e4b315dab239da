"""Config values checked where they enter: before anything is built, each entry point checks the numbers of its
config and stops at the first bad one with a ConfigError naming the key, what was expected, what was found and the
fix (components check their own options when they are built; datasets check their files when they are opened)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from omegaconf import DictConfig, OmegaConf

from framework.build import ConfigError
from framework.execution import KERNEL_CHOICES
from framework.splat.sh import MAX_SH_DEGREE

_ABSENT = object()


def _value(cfg: DictConfig, key: str) -> Any:
    return OmegaConf.select(cfg, key, default=_ABSENT, throw_on_missing=False)


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _expect(cfg: DictConfig, key: str, ok: Callable[[Any], bool], expected: str, fix: str) -> None:
    value = _value(cfg, key)
    if value is _ABSENT or value is None:
        return
    if not ok(value):
        raise ConfigError(f"config key {key}: expected {expected}, found {value!r}. {fix}")


def _positive_int(cfg: DictConfig, key: str, what: str, example: int) -> None:
    _expect(cfg, key, lambda v: _is_int(v) and v >= 1, f"a positive integer ({what})", f"For example {key}={example}.")


def check_no_missing(cfg: DictConfig) -> None:
    """No key left at `???` (a value its config file asks the command line for, e.g. data.root of zju_mocap)."""
    missing = sorted(k for k in OmegaConf.missing_keys(cfg) if not k.startswith("hydra"))
    if missing:
        key = missing[0]
        raise ConfigError(
            f"config key {key}: expected a value, found none ('???' in its config file). Set it on the "
            f"command line, e.g. {key}=<value>."
        )


def check_train_config(cfg: DictConfig) -> None:
    """The numbers of a `python -m framework.train` config (profile values arrive through interpolation)."""
    check_no_missing(cfg)
    for key, what, example in (
        ("trainer.max_steps", "optimisation steps", 3000),
        ("trainer.val_every", "steps between validations", 500),
        ("trainer.log_every", "steps between logged values", 25),
        ("callbacks.checkpoint_every", "steps between last.ckpt saves", 250),
        ("gaussians.num", "initial Gaussians", 10000),
        ("gaussians.sh_increase_every", "steps per SH degree", 1000),
        ("eval.val_max_items", "validation images", 6),
        ("data.resolution", "image side in pixels", 128),
        ("data.num_views", "cameras", 12),
        ("data.num_frames", "frames", 60),
        ("data.num_train_views", "cameras", 24),
        ("data.num_test_views", "cameras", 6),
        ("data.supersample", "rays per pixel side", 1),
        ("threads", "CPU threads", 2),
        ("small_work_threads", "CPU threads for the step's losses, optimizer and bookkeeping", 1),
    ):
        _positive_int(cfg, key, what, example)
    _expect(
        cfg,
        "callbacks.image_every",
        lambda v: _is_int(v) and v >= 0,
        "an integer >= 0 (0: no image grids)",
        "For example callbacks.image_every=500.",
    )
    _expect(
        cfg,
        "gaussians.sh_degree",
        lambda v: _is_int(v) and 0 <= v <= MAX_SH_DEGREE,
        f"an integer in 0..{MAX_SH_DEGREE} (real spherical harmonics up to degree 3)",
        f"Use gaussians.sh_degree={MAX_SH_DEGREE}.",
    )
    _expect(
        cfg,
        "gaussians.opacity",
        lambda v: _is_number(v) and 0 < v < 1,
        "an initial opacity in (0, 1)",
        "For example gaussians.opacity=0.1.",
    )
    _expect(
        cfg,
        "stages.stage1_steps",
        lambda v: _is_int(v) and v >= 0,
        "an integer >= 0 (0: no stage 1)",
        "For example stages.stage1_steps=1000.",
    )
    stage1, steps = _value(cfg, "stages.stage1_steps"), _value(cfg, "trainer.max_steps")
    fast = bool(_value(cfg, "trainer.fast_dev_run") not in (_ABSENT, None, False))
    if _is_int(stage1) and _is_int(steps) and 0 < steps <= stage1 and not fast:
        raise ConfigError(
            f"config key stages.stage1_steps: expected fewer steps than the run's trainer.max_steps={steps}, found "
            f"{stage1}; stage 2 (the corrector and the blend-weight residual) would never start. Lower "
            f"stages.stage1_steps or raise trainer.max_steps."
        )
    terms = _value(cfg, "loss.terms")
    if isinstance(terms, DictConfig):
        for name in terms:
            key = f"loss.terms.{name}.weight"
            _expect(
                cfg,
                key,
                lambda v: _is_number(v) and v >= 0,
                "a finite weight >= 0 (0 disables the term)",
                f"For example {key}=0.2.",
            )
    rates = _value(cfg, "optim.lr")
    if isinstance(rates, DictConfig):
        for name in rates:
            _expect(
                cfg,
                f"optim.lr.{name}",
                lambda v: _is_number(v) and v >= 0,
                "a finite learning rate >= 0",
                f"For example optim.lr.{name}=1e-3.",
            )
    _expect(
        cfg,
        "execution.kernels",
        lambda v: v in KERNEL_CHOICES,
        f"one of {', '.join(KERNEL_CHOICES)} (framework/execution.py)",
        "For example execution.kernels=auto.",
    )
    _expect(
        cfg,
        "optim.means_final_ratio",
        lambda v: _is_number(v) and 0 < v <= 1,
        "a ratio in (0, 1]",
        "For example optim.means_final_ratio=0.01.",
    )


def check_evaluate_config(cfg: DictConfig) -> None:
    """`python -m framework.evaluate`: the checkpoint is required; splits and metrics are lists of names."""
    if OmegaConf.is_missing(cfg, "ckpt"):
        raise ConfigError(
            "config key ckpt: expected the path of a checkpoint, found none. Pass "
            "ckpt=<run>/checkpoints/last.ckpt (or final.ckpt)."
        )
    for key, example in (("splits", "[novel_view,novel_pose]"), ("metrics", "[psnr,ssim]")):
        _expect(
            cfg,
            key,
            lambda v: OmegaConf.is_list(v) and all(isinstance(x, str) for x in v),
            "a list of names",
            f"For example {key}={example}.",
        )


def check_render_config(cfg: DictConfig) -> None:
    """`python -m framework.render`: the checkpoint is required; sizes and counts are positive."""
    if OmegaConf.is_missing(cfg, "ckpt"):
        raise ConfigError(
            "config key ckpt: expected the path of a checkpoint, found none. Pass "
            "ckpt=<run>/checkpoints/last.ckpt (or final.ckpt)."
        )
    _expect(cfg, "cameras", lambda v: v in ("orbit", "fixed"), "'orbit' or 'fixed'", "For example cameras=orbit.")
    _positive_int(cfg, "resolution", "image side in pixels; null keeps the training resolution", 512)
    _positive_int(cfg, "fps", "frames per second of the video", 25)
    _positive_int(cfg, "max_frames", "frames to render; null renders the whole motion", 100)
    _expect(cfg, "camera_index", lambda v: _is_int(v) and v >= 0, "a camera index >= 0", "For example camera_index=0.")
    _expect(cfg, "orbit_turns", _is_number, "a finite number of turns", "For example orbit_turns=1.0.")


def check_prune_config(cfg: DictConfig) -> None:
    """`python -m framework.prune` (and `framework.export prune=true`): tolerances are numbers >= 0 or null (the
    fold and prune tolerances also `auto`), counts are integers >= 0."""
    if OmegaConf.is_missing(cfg, "ckpt"):
        raise ConfigError(
            "config key ckpt: expected the path of a checkpoint, found none. Pass ckpt=<run>/checkpoints/final.ckpt."
        )
    for key in ("min_weight", "sh_tolerance"):
        _expect(
            cfg,
            key,
            lambda v: _is_number(v) and v >= 0,
            "a finite number >= 0 (null switches the step off)",
            f"For example {key}=0.004.",
        )
    for key, off, example in (
        ("fold_tolerance", "F_a is never folded", 0.004),
        ("prune_tolerance", "no faint-Gaussian pruning", 0.03),
    ):
        _expect(
            cfg,
            key,
            lambda v: v == "auto" or (_is_number(v) and v >= 0),
            f"'auto' or a finite number >= 0 (null: {off})",
            f"For example {key}={example}.",
        )
    for key, what in (
        ("refit_steps", "0: no refit"),
        ("warmup", "untimed frames"),
        ("repeats", "timed frames"),
        ("rounds", "interleaved timing rounds"),
    ):
        _expect(cfg, key, lambda v: _is_int(v) and v >= 0, f"an integer >= 0 ({what})", f"For example {key}=300.")
    _positive_int(cfg, "prune_rounds", "1: prune once, then refit; more: prune and refit again", 2)
    _known_rasterizer(cfg, "timing_rasterizer")


def _known_rasterizer(cfg: DictConfig, key: str) -> None:
    """`key` names a rasterizer that runs here, or is null; checked before the compaction's minutes of work."""
    name = cfg.get(key)
    if name is None:
        return
    from framework.plugins import load_plugins
    from framework.registry import RASTERIZERS, RegistryError

    load_plugins()
    try:
        RASTERIZERS.get(str(name))
    except RegistryError as exc:
        raise ConfigError(f"config key {key}: {exc} Or {key}=null: the rasterizer the model trained with.") from None

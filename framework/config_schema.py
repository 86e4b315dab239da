"""The training config's types: the top-level keys and the engine-owned groups (gaussians, optim, trainer, callbacks,
paths, profile) as dataclasses in Hydra's ConfigStore, so a mistyped value (`trainer.max_steps=abc`) fails while the
config is composed, with the key and the expected type (framework.cli words it in one line).

`conf/train.yaml` lists `schema_train` first in its defaults: the YAML files are merged onto these types. The YAML
holds the values and their comments; a default here is what a stored config that lacks the key (a checkpoint written
before the key existed) reads, the YAML's own value wherever one group option fits all. Groups whose keys depend on
the plugin chosen (data, body, corrector, deformer, rasterizer, loss, densifier, logger) stay untyped here: their
components' constructors check them.

`training_settings(cfg)` is the one place a stored config (a checkpoint's, possibly older) is read as these types.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Optional

from omegaconf import MISSING, OmegaConf

# OmegaConf reads the annotations at run time: `Optional[int]`, not `int | None` (unsupported in omegaconf 2.3)
# ruff: noqa: UP007, UP045


@dataclass
class ExecutionConfig:
    kernels: str = "auto"  #: auto (compiled CPU kernels on a CPU, torch elsewhere) | compiled | torch


@dataclass
class Stages:
    stage1_steps: int = 0  #: steps of stage 1 (Gaussians + joints only) before the corrector / weight residual start


@dataclass
class PoseRefine:
    enabled: bool = False  #: per-frame joint-rotation residuals + shared joint-position residuals


@dataclass
class Divergence:
    action: str = "stop"  #: stop | rollback, on a NaN/Inf in the loss, a gradient or a parameter
    lr_factor: float = 0.5  #: rollback: learning rates are multiplied by this at each rollback
    max_rollbacks: int = 3  #: rollback: stop after this many
    deferred: Any = "auto"  #: true | false | auto: skip a bad update on the device, read the check later


@dataclass
class Scene:
    survey: bool = False  #: measure the training data first
    auto: bool = False  #: apply the choices of conf/scene/auto.yaml
    frozen_joints: list[str] = field(default_factory=list)  #: joints held at their mean training rotation
    max_frames: int = 12  #: frames sampled for the survey's colour statistics
    blur_px: float = 1.0  #: Gaussian low-pass (pixels) before colours are compared
    moving_deg: float = 0.5  #: a joint moves when its rotation range exceeds this
    fold_corrector: bool = True  #: whether compaction may fold F_a into the Gaussians
    thresholds: dict[str, Any] = field(default_factory=dict)  #: +scene=auto's rules (conf/scene/auto.yaml)


@dataclass
class DataLoader:
    num_workers: int = 0  #: processes that decode frames while the step runs


@dataclass
class Eval:
    after_fit: bool = True  #: evaluate the final model on `splits`
    splits: list[str] = field(default_factory=lambda: ["novel_view"])  #: held-out splits evaluated after training
    val_split: str = "novel_view"  #: the split validated on during training
    val_max_items: int = 6  #: frames of it per validation
    metrics: list[str] = field(default_factory=lambda: ["psnr", "ssim", "lpips_alex"])  #: image metrics
    fps_frames: int = 20  #: render fps of the final model: median of this many frames; 0 skips it
    fps_warmup: int = 3  #: frames rendered before timing starts


@dataclass
class Gaussians:
    num: int = MISSING  #: Gaussians at the start
    sh_degree: int = MISSING  #: highest spherical-harmonics degree
    sh_increase_every: int = 1000  #: one SH degree more every this many steps
    opacity: float = 0.1  #: initial opacity


@dataclass
class LearningRates:
    means: float = 1.6e-4  #: scaled by the scene radius, decayed to `means_final_ratio` of it
    quats: float = 1.0e-3
    log_scales: float = 5.0e-3
    opacity_logits: float = 5.0e-2
    sh0: float = 2.5e-3
    shN: float = 1.25e-4  # noqa: N815  (the parameter's name)
    latents: float = 1.0e-3
    networks: float = 1.0e-3  #: corrector and deformer MLPs
    pose: float = 1.0e-4  #: per-frame pose residuals
    joints: float = 1.0e-4  #: joint-position residuals


@dataclass
class Optim:
    lr: LearningRates = field(default_factory=LearningRates)  #: Adam learning rates per parameter group
    means_final_ratio: float = 0.01  #: the means' learning rate ends at this fraction of its start


@dataclass
class Trainer:
    max_steps: int = 3000  #: training steps
    max_time: Optional[str] = None  #: DD:HH:MM:SS wall-clock budget
    accelerator: str = "auto"  #: auto | cpu | gpu
    precision: str = "32-true"  #: Lightning's precision
    val_every: int = 500  #: steps between validations
    log_every: int = 25  #: steps between logged scalars
    fast_dev_run: bool = False  #: one step of each loop (a smoke test)
    limit_val_batches: Any = 1.0  #: a fraction (float) or a number of batches (int) per validation


@dataclass
class Callbacks:
    checkpoint_every: int = 250  #: steps between `last.ckpt` saves
    image_every: int = 500  #: steps between render|gt|error grids in TensorBoard
    image_views: int = 2  #: views per grid
    progress_bar: bool = True  #: a progress line on the terminal


@dataclass
class Paths:
    root: str = "outputs"  #: where runs are written, relative to the working directory
    output_dir: str = MISSING  #: this run's folder (Hydra's)


@dataclass
class Schedule:
    """Milestones as fractions of `max_steps` (a number, or a ratio such as 5000/30000)."""

    stage1: Any = MISSING
    densify_start: Any = MISSING
    densify_stop: Any = MISSING
    densify_every: Any = MISSING
    first_reset: Any = MISSING
    reset_every: Any = MISSING
    sh_every: Any = MISSING
    val_every: Any = MISSING


@dataclass
class Profile:
    name: str = MISSING  #: cpu | gpu | ablation
    resolution: int = MISSING  #: image size (pixels) of the synthetic studio
    num_views: int = MISSING  #: cameras
    num_frames: int = MISSING  #: frames
    num_gaussians: int = MISSING  #: Gaussians at the start
    max_steps: int = MISSING  #: training steps
    max_gaussians: int = MISSING  #: densification's cap
    schedule: Schedule = field(default_factory=Schedule)  #: milestones as fractions of max_steps
    loader_workers: int = 0  #: DataLoader processes while the step runs (data_loader.num_workers)


@dataclass
class Train:
    """The primary config of `python -m framework.train` (conf/train.yaml)."""

    data: Any = None  #: the dataset (plugin-chosen group: checked by its constructor)
    body: Any = None
    gaussians: Gaussians = field(default_factory=Gaussians)
    corrector: Any = None
    deformer: Any = None
    rasterizer: Any = None
    loss: Any = None
    densifier: Any = None
    optim: Optim = field(default_factory=Optim)
    trainer: Trainer = field(default_factory=Trainer)
    logger: Any = None
    callbacks: Callbacks = field(default_factory=Callbacks)
    paths: Paths = field(default_factory=Paths)
    profile: Profile = field(default_factory=Profile)

    task_name: str = "train"  #: the run's name (an experiment sets its own)
    seed: int = 0  #: random seed of initialisation, sampling and densification
    threads: Optional[int] = None  #: torch CPU threads; null keeps torch's default
    small_work_threads: Optional[int] = 1  #: threads for a CPU step's losses and bookkeeping (null: all)
    execution: ExecutionConfig = field(default_factory=ExecutionConfig)
    metric: str = "novel_view/psnr"  #: returned to Hydra sweepers
    ckpt: Optional[str] = None  #: resume from this checkpoint
    ckpt_path: Optional[str] = None  #: the older name of ckpt
    background: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  #: RGB behind the avatar
    stages: Stages = field(default_factory=Stages)
    pose_refine: PoseRefine = field(default_factory=PoseRefine)
    divergence: Divergence = field(default_factory=Divergence)
    scene: Scene = field(default_factory=Scene)
    data_loader: DataLoader = field(default_factory=DataLoader)
    eval: Eval = field(default_factory=Eval)


# the groups whose keys depend on the plugin chosen: untyped here, read from the config itself
PLUGIN_GROUPS = ("data", "body", "corrector", "deformer", "rasterizer", "loss", "densifier", "logger")


def register() -> None:
    """`schema_train` in Hydra's ConfigStore (conf/train.yaml's first default)."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name="schema_train", node=Train)


def _known(node: Any, cls: type) -> Any:
    """`node` without the keys `cls` (a dataclass) does not declare, at every typed level (an older checkpoint's
    config may hold keys since removed: `compile`, `scene.profile`)."""
    if not isinstance(node, Mapping):
        return node
    fields = {f.name: f for f in dataclasses.fields(cls)}
    out = {}
    for key, value in node.items():
        f = fields.get(str(key))
        if f is None:
            continue
        kind = f.default_factory() if f.default_factory is not dataclasses.MISSING else None  # type: ignore[misc]
        out[key] = _known(value, type(kind)) if dataclasses.is_dataclass(kind) else value
    return out


def training_settings(cfg: Mapping[str, Any]) -> Train:
    """A training config (composed, or a checkpoint's stored one) as the typed `Train`: a key the config lacks reads
    as the schema's default, a key the schema does not know is left out, a value of the wrong type raises
    omegaconf's ValidationError. The plugin-chosen groups are left out (None): their components read them from the
    config itself, and a copy here could go stale when a tool replaces one (compaction's deformer)."""
    if OmegaConf.is_config(cfg):
        cfg = OmegaConf.to_container(cfg, resolve=True)  # type: ignore[assignment]
    engine = {k: v for k, v in _known(cfg, Train).items() if k not in PLUGIN_GROUPS}
    typed = OmegaConf.merge(OmegaConf.structured(Train), engine)
    return OmegaConf.to_object(typed)  # type: ignore[return-value]

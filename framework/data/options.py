"""`SequenceOptions`: the dataset keys every reader of a calibrated multi-view sequence takes (zju_mocap, easymocap,
synthetic_studio), in one place with their defaults and their checks. A dataset plugin keeps only its layout's own
keys (root, protocol, cameras, ...) and builds these from the rest of its config (`from_config`), so a key is declared,
documented and checked once instead of once per plugin. Key names follow `framework.dataset_keys`.

Not a Hydra structured-config schema: the data group's options are four datasets with different layout keys, and
OmegaConf cannot type a view given as an index or a camera name; a misspelled key is caught by Hydra's struct mode on
the command line and by `from_config` when the dataset is built.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, ClassVar

from framework.dataset_keys import split_config

BOUNDARY_CACHES = ("memory", "disk")


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


@dataclass(frozen=True)
class SequenceOptions:
    """Which views and frames each split takes, how images are prepared, and what is cached (defaults: full-size
    images, black background, the paper's 5 px boundary band in output pixels)."""

    train_views: tuple[int | str, ...] | None = None  # view indices (easymocap: or camera names); None: the layout's
    test_views: tuple[int | str, ...] | None = None  # None: every view not trained on (view 0 when that leaves none)
    novel_pose_views: tuple[int | str, ...] | None = None  # None: the test views
    train_frames: tuple[int | None, ...] | None = None  # [start, end, step] (end exclusive) or frames; None: all
    novel_pose_frames: tuple[int | None, ...] | None = None  # the held-out motion, as train_frames
    eval_frame_step: int | None = None  # evaluation splits take every n-th frame; None: the layout's (else 1)
    downscale: float = 1.0  # image size divisor (>= 1); K is rescaled to match
    boundary_px: int = 5  # M_b's half-width in pixels at boundary_ref_side (0: no band)
    boundary_ref_side: int | None = None  # image side boundary_px holds at; None: boundary_px in output pixels
    mask_dir: str = "auto"  # the layout's mask folder; auto: its preferred one that exists
    body: str | None = None  # body registry name of the poses; None: the params' "body" key, else smpl
    white_background: bool = False  # composite over white instead of black
    mask_background: bool = True  # replace the captured background by the background colour using the mask
    bounds_margin: float = 0.1  # metres added around the posed subject's world box
    cache_mb: float = 512.0  # LRU budget for decoded uint8 images and masks (0: none)
    boundary_cache: str = "memory"  # memory | disk (cache_dir, else <root>/.splatrig_cache, else the project cache)
    cache_dir: str | None = None

    VIEW_KEYS: ClassVar[tuple[str, ...]] = ("train_views", "test_views", "novel_pose_views")
    FRAME_KEYS: ClassVar[tuple[str, ...]] = ("train_frames", "novel_pose_frames")

    def __post_init__(self) -> None:
        for key in self.VIEW_KEYS:
            views = getattr(self, key)
            if views is None:
                continue
            views = tuple(views)
            if not views or not all((_int(v) and v >= 0) or isinstance(v, str) for v in views):
                raise ValueError(
                    f"{key} must be a non-empty list of view indices >= 0 (or camera names), got {list(views)}"
                )
            object.__setattr__(self, key, views)
        for key in self.FRAME_KEYS:
            spec = getattr(self, key)
            if spec is None:
                continue
            spec = tuple(spec)
            if not spec or not all(_int(f) or f is None for f in spec):
                raise ValueError(
                    f"{key} must be [start, end, step] (end exclusive) or a list of frames, got {list(spec)}"
                )
            object.__setattr__(self, key, spec)
        if self.eval_frame_step is not None and not (_int(self.eval_frame_step) and self.eval_frame_step >= 1):
            raise ValueError(f"eval_frame_step must be an integer >= 1 (or null), got {self.eval_frame_step!r}")
        if not (_number(self.downscale) and self.downscale >= 1.0):
            raise ValueError(f"downscale must be >= 1 (an image size divisor), got {self.downscale!r}")
        if not (_int(self.boundary_px) and self.boundary_px >= 0):
            raise ValueError(f"boundary_px must be an integer >= 0 (0: no band), got {self.boundary_px!r}")
        if self.boundary_ref_side is not None and not (_int(self.boundary_ref_side) and self.boundary_ref_side >= 1):
            raise ValueError(f"boundary_ref_side must be an image side >= 1 (or null), got {self.boundary_ref_side!r}")
        for key in ("bounds_margin", "cache_mb"):
            if not (_number(getattr(self, key)) and getattr(self, key) >= 0):
                raise ValueError(f"{key} must be a finite number >= 0, got {getattr(self, key)!r}")
        for key in ("white_background", "mask_background"):
            if not isinstance(getattr(self, key), bool):
                raise ValueError(f"{key} must be true or false, got {getattr(self, key)!r}")
        if self.boundary_cache not in BOUNDARY_CACHES:
            raise ValueError(f"boundary_cache must be 'memory' or 'disk', got {self.boundary_cache!r}")
        for key in ("downscale", "bounds_margin", "cache_mb"):
            object.__setattr__(self, key, float(getattr(self, key)))

    @classmethod
    def from_config(cls, config: dict[str, Any], dataset: str) -> SequenceOptions:
        """The options of a dataset's config keys (those its layout does not take); an unknown key is one ValueError
        naming it (`framework.dataset_keys.split_config`)."""
        return cls(**split_config(config, cls, dataset=dataset)[0])

    def with_defaults(self, **layout: Any) -> SequenceOptions:
        """These options with each None key among `layout` set to the layout's value (a protocol's views, the
        studio's held-out cameras): what the config gives explicitly wins."""
        return replace(self, **{k: v for k, v in layout.items() if getattr(self, k) is None})

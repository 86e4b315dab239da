"""Multi-view datasets: calibrated cameras, images, masks and (for bodies) per-frame poses."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from framework.types import Cameras, FrameBatch


class MultiViewDataset(torch.utils.data.Dataset, ABC):
    """One split (train / novel_view / novel_pose) of a multi-view sequence; item i is one (frame, view) sample.

    Attributes every dataset sets:
      cameras: Cameras of every view in the rig (C = number of views).
      frame_ids: list[int] of the frames in this split (indices into the whole sequence).
      num_frames_total: frames in the whole sequence (pose refinement tables are this long).
      body_name: registry name of the body model the poses belong to, or None for static scenes.
      bounds: Tensor [2, 3], a box holding the subject (canonical for bodies, world for static scenes).
    """

    registry_name: str = ""
    #: The folder the data is read from (scene surveys are stored beside it), or None when it has none.
    root: Path | None = None
    #: The views (camera indices into `cameras`) this split uses.
    views: Sequence[int] = ()
    cameras: Cameras
    frame_ids: list[int]
    num_frames_total: int
    body_name: str | None
    bounds: Tensor

    @abstractmethod
    def __len__(self) -> int: ...

    @abstractmethod
    def __getitem__(self, index: int) -> FrameBatch:
        """A FrameBatch with B = 1."""

    def sample(self, index: int) -> tuple[int, int]:
        """(frame, view) of item `index`; this default reads the item, a dataset that knows it without override it."""
        batch = self[index]
        return int(batch.frame[0]), int(batch.view[0]) if batch.view is not None else 0

    def roots(self) -> Tensor | None:
        """[num_frames_total, 4, 4] root transforms applied after the body model, or None when there are none."""
        return None

    def has_vertices(self) -> bool:
        """Whether `vertices` can read the stored posed body vertices of a frame."""
        return False

    def vertices(self, frame: int) -> Tensor:
        """[V, 3] the stored posed world vertices of `frame` (for checks, previews and the scene survey)."""
        raise ValueError(f"dataset '{self.registry_name}' stores no body vertices")

    def poses(self) -> Tensor | None:
        """[num_frames_total, J, 3] stored poses of the whole sequence (None for static scenes)."""
        return None

    def fitted_betas(self) -> Tensor | None:
        """[S] the body shape the poses were fitted with (mean over the split's frames); None when the data has none.
        SMPL-family bodies whose config leaves `betas` null take it, so the skeleton matches the poses."""
        return None

    def body_box(self, frame: int) -> np.ndarray | None:
        """[2, 3] world box of `frame`'s posed body for the body-box metrics (`framework.evaluation.body_box`: the
        stored body vertices' box grown by 5 cm), or None when the dataset has no body vertices."""
        return None

    def initial_points(self) -> Tensor | None:
        """[M, 3] points to initialise Gaussians from when there is no body (None: sample inside `bounds`)."""
        return None

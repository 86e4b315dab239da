"""Appearance correctors: pose-dependent residuals on canonical Gaussians (the paper's F_a)."""

from __future__ import annotations

from abc import ABC, abstractmethod

from torch import Tensor, nn

from framework.execution import ExecutionMixin
from framework.types import Gaussians


class Corrector(nn.Module, ExecutionMixin, ABC):
    """Maps (target pose, per-Gaussian code) to corrected canonical Gaussians.

    Contract: positions are never changed; the pose is gradient-stopped by the corrector itself; opacity and scale
    residuals are added in raw (logit / log) space; the rotation residual is a quaternion applied as dr * r.
    `enabled` is switched by the stage callback: a disabled corrector returns its input unchanged.
    """

    registry_name: str = ""

    def __init__(self) -> None:
        super().__init__()
        self.enabled = True

    def bind(self, num_pose_features: int) -> None:  # noqa: B027 - optional hook
        """Called once the body's pose size is known, before training; build layers here if they depend on it."""

    def corrected_rows(self) -> Tensor | None:
        """[M] long: the Gaussians still corrected (empty: every one) by a corrector that can be restricted to a
        subset, which compaction's partial fold needs; None: it cannot be."""
        return None

    def set_corrected_rows(self, rows: Tensor) -> None:
        """Correct only the Gaussians `rows` [M] long (empty: every one); only called when `corrected_rows` is not
        None."""
        raise NotImplementedError(f"corrector '{self.registry_name}' cannot be restricted to some Gaussians")

    @abstractmethod
    def forward(self, gaussians: Gaussians, pose: Tensor) -> Gaussians:
        """gaussians: canonical; pose: [P] flattened pose features of the target frame."""

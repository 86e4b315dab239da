"""`posenc`: ablation of F_a with a positional encoding of the canonical position in place of the latent code."""

from __future__ import annotations

from torch import Tensor

from framework.model.corrector_mlp import MLPCorrector
from framework.model.posenc import posenc, posenc_dim
from framework.registry import register
from framework.types import Gaussians


@register("corrector", "posenc")
class PosencCorrector(MLPCorrector):
    """Per-Gaussian feature = posenc(x / extent, num_freqs) (21-dim for the paper's 3 frequencies).

    The position is detached: the code is a fixed function of where the Gaussian is, and appearance residuals must
    not drag Gaussians around (positions are fitted by the deformation and image losses). `extent` (metres) maps the
    canonical body (|x| <~ 1 m) into [-1, 1], where the lowest frequency covers the body once.
    """

    def __init__(self, num_freqs: int = 3, extent: float = 1.0, **kwargs) -> None:
        super().__init__(**kwargs)
        if extent <= 0:
            raise ValueError(f"corrector 'posenc': extent must be positive (metres), got {extent}.")
        self.num_freqs, self.extent = num_freqs, float(extent)
        self.feature_dim = posenc_dim(num_freqs)

    def features(self, gaussians: Gaussians) -> Tensor:
        return posenc(gaussians.means.detach() / self.extent, self.num_freqs, self.execution)

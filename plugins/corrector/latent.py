"""`latent`: the paper's F_a on [pose, the Gaussian's learnable 9-dim latent code]."""

from __future__ import annotations

from torch import Tensor

from framework.model.corrector_mlp import MLPCorrector
from framework.registry import register
from framework.types import Gaussians


@register("corrector", "latent")
class LatentCorrector(MLPCorrector):
    """Per-Gaussian feature = its latent code f_i (learned with the Gaussians, initialised by positional encoding)."""

    feature_dim = 9

    def features(self, gaussians: Gaussians) -> Tensor:
        if gaussians.latents is None or gaussians.latents.shape[-1] != self.feature_dim:
            found = None if gaussians.latents is None else tuple(gaussians.latents.shape)
            raise ValueError(
                f"corrector 'latent': Gaussians need latents [N, {self.feature_dim}], found {found}; initialise them "
                "with framework.model.gaussian_init (which sets 9-dim codes) or use corrector=posenc."
            )
        return gaussians.latents

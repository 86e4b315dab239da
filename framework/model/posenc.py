"""NeRF-style positional encoding, shared by the latent initialisation, the `posenc` corrector and F_dw.

gamma(x) = [x, sin(2^0 pi x), cos(2^0 pi x), ..., sin(2^(F-1) pi x), cos(2^(F-1) pi x)], per coordinate, so a 3-vector
with F frequencies gives 3 + 6F features: 9 for F = 1 (the latent code's initial value), 21 for F = 3 (the paper's
`posenc` corrector). Inputs are expected roughly in [-1, 1] (see `normalize_to_bounds`): the lowest frequency then
covers the whole box once, so distinct positions get distinct codes.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from framework.execution import COMPILED, Execution


def posenc_dim(num_freqs: int, in_dim: int = 3) -> int:
    """Output width of `posenc` for `in_dim` inputs."""
    return in_dim * (1 + 2 * num_freqs)


def posenc(x: Tensor, num_freqs: int, execution: Execution = COMPILED) -> Tensor:
    """x [..., D] -> [..., D * (1 + 2 * num_freqs)], ordered [x, sin f0, cos f0, sin f1, cos f1, ...] (each block D).

    Where `execution` compiles x, the compiled loop of `framework.kernels.posenc` (the same values from one sine and
    cosine per coordinate); otherwise the torch operations below."""
    if num_freqs < 0:
        raise ValueError(f"posenc: num_freqs must be >= 0, got {num_freqs}.")
    if num_freqs and execution.compiled(x):
        from framework.kernels.posenc import posenc_compiled  # imports numba: first use only

        return posenc_compiled(x, num_freqs)
    feats = [x]
    for k in range(num_freqs):
        arg = (2.0**k * math.pi) * x
        feats += [torch.sin(arg), torch.cos(arg)]
    return torch.cat(feats, dim=-1)


def normalize_to_bounds(x: Tensor, bounds: Tensor | None) -> Tensor:
    """Map positions [..., 3] from the box `bounds` [2, 3] (min, max) to [-1, 1]; identity when bounds is None."""
    if bounds is None:
        return x
    bounds = torch.as_tensor(bounds, dtype=x.dtype, device=x.device)
    lo, hi = bounds[0], bounds[1]
    return 2.0 * (x - lo) / (hi - lo).clamp_min(1e-12) - 1.0

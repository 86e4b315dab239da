"""`lbs_residual`: LBS whose grid weights are refined by the paper's F_dw (switched on in stage 2)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from framework.interfaces.body import BodyModel
from framework.model.lbs_deformer import LBSDeformerBase
from framework.model.posenc import normalize_to_bounds, posenc, posenc_dim
from framework.registry import register


@register("deformer", "lbs_residual")
class LBSResidualDeformer(LBSDeformerBase):
    """Grid weights w0 refined by dw = F_dw(x) = MLP(posenc(x)) with a zero-initialised last layer (so training starts
    from the grid weights), in one of three forms (`residual`):

    - "additive" (the paper, as written): w = w0 + dw. Nothing keeps the result non-negative or summing to one; it
      starts as the grid's partition of unity, and L_w regularises these very weights.
    - "additive_normalised": w = max(w0 + dw, 0) / sum_k max(w0 + dw, 0)_k, the paper's sum made a valid weight set
      (non-negative, summing to one, so a rigid motion of every bone moves the Gaussian rigidly). A joint the grid
      gives no weight gains none (the clamp's gradient is 0 there).
    - "softmax": w = softmax(log(w0 + eps) + dw) = normalise((w0 + eps) exp(dw)). The residual acts on log-weights,
      so the weights stay non-negative and sum to one by construction. `eps` (1e-6) lets a joint the grid gives no
      weight gain some if the data demands (dw must reach about log(w / eps) ~ 14), while leaking at most J * eps.

    Disabled (stage 1) it is plain `lbs` and its parameters are unused. After training, `bake` stores the final
    weights per Gaussian so F_dw is not evaluated at inference. The compiled CPU loops of
    `framework.kernels.skin_weights` know "additive" and "softmax"; "additive_normalised" runs in torch.
    """

    RESIDUALS = ("additive", "additive_normalised", "softmax")

    def __init__(
        self,
        hidden: int = 32,
        layers: int = 4,
        num_freqs: int = 4,
        eps: float = 1e-6,
        residual: str = "softmax",
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        if residual not in self.RESIDUALS:
            raise ValueError(f"deformer 'lbs_residual': residual must be one of {self.RESIDUALS}, got '{residual}'.")
        self.enabled = True
        self.hidden, self.num_layers, self.num_freqs, self.eps = hidden, layers, num_freqs, eps
        self.combine = residual
        self.mlp: nn.Sequential | None = None

    def bind(self, body: BodyModel | None, bounds: Tensor | None) -> None:
        super().bind(body, bounds)
        dims = [posenc_dim(self.num_freqs)] + [self.hidden] * (self.num_layers - 1)
        mods: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:], strict=True):
            # in place, as F_a's trunk: the activation overwrites the product it follows (whose backward does not read
            # it), so no [7N, hidden] temporary is allocated per layer
            mods += [nn.Linear(a, b), nn.ReLU(inplace=True)]
        last = nn.Linear(dims[-1], self.field.num_joints)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.mlp = nn.Sequential(*mods, last)

    @property
    def refines(self) -> bool:
        return self.enabled and self.mlp is not None

    def release_after_bake(self) -> str | None:
        """F_dw is unused once the weights are baked: its parameters leave the checkpoint, which loads as `lbs`."""
        if self.mlp is None:
            return None
        self.mlp = None
        return "lbs"

    def rebuilds_weights(self, means: Tensor, weights: Tensor) -> bool:
        return self.mlp is None and super().rebuilds_weights(means, weights)

    def residual(self, points: Tensor) -> tuple[str, Tensor | None]:
        if not self.refines:
            return "none", None
        x = normalize_to_bounds(points, self.field.bounds)
        enc = posenc(x, self.num_freqs, self.execution).to(points.dtype)  # [..., D]
        # through the MLP as one [M, D] matrix: on a [N, 7, D] input torch's linear backward copies every activation
        # and gradient once more (1.4x the time of the same MLP on the flat rows, measured at 56k points)
        dw = self.mlp(enc.reshape(-1, enc.shape[-1]))  # [M, J]
        return self.combine, dw.reshape(*enc.shape[:-1], dw.shape[-1])  # [..., J]

    def _weights_compiled(self, points: Tensor) -> bool:
        return self.combine != "additive_normalised" and super()._weights_compiled(points)

    @property
    def residual_eps(self) -> float:
        return self.eps

    def refine(self, points: Tensor, w: Tensor) -> Tensor:
        grid = w
        combine, dw = self.residual(points)
        if dw is None:
            return w
        if combine == "additive":
            return w + dw
        if combine == "additive_normalised":
            w = (w + dw).clamp_min(0.0)
            total = w.sum(-1, keepdim=True)
            # every weight clamped to 0 (F_dw far off): fall back to the grid's weights rather than divide by 0
            return torch.where(total > 0, w / torch.where(total > 0, total, torch.ones_like(total)), grid)
        return torch.softmax(torch.log(w + self.eps) + dw, dim=-1)

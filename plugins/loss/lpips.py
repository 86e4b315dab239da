"""Perceptual loss with our LPIPS module (AlexNet by default), as in the paper's "w/ L_p" rows."""

from __future__ import annotations

from torch import Tensor

from framework.interfaces.loss import Loss
from framework.registry import register
from framework.types import FrameBatch, RenderOutput


def _requires() -> str | None:
    from framework.image.lpips import LPIPSWeightsMissing, weights_file

    try:
        weights_file("alex")
    except LPIPSWeightsMissing as exc:
        return str(exc)
    return None


@register("loss", "lpips", requires=_requires)
class LPIPSLoss(Loss):
    """mean over the batch of LPIPS(rgb, image), inputs in [0, 1].

    The frozen network is kept out of the module tree on purpose: it would otherwise enter every checkpoint (10-60
    MB) and any optimizer built from `module.parameters()`. It follows the input's device lazily.
    """

    def __init__(self, net: str = "alex") -> None:
        super().__init__()
        from framework.image.lpips import LPIPS

        self.net = net
        self.__dict__["_model"] = LPIPS(net)  # bypasses nn.Module registration (see class docstring)

    def forward(self, render: RenderOutput, batch: FrameBatch, aux: dict[str, Tensor]) -> Tensor:
        model = self.__dict__["_model"]
        if model.shift.device != render.rgb.device:
            model.to(render.rgb.device)
        pred = render.rgb.permute(0, 3, 1, 2)  # [B, 3, H, W]
        target = batch.image.permute(0, 3, 1, 2).to(pred.dtype)
        return model(pred, target, normalize=True).mean()

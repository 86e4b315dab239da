"""LPIPS metrics (lower is better): AlexNet, the common choice in avatar papers, and VGG16, which some peers report."""

from __future__ import annotations

import torch
from torch import Tensor

from framework.interfaces.metric import Metric
from framework.registry import register


def _requires(net: str):
    def check() -> str | None:
        from framework.image.lpips import LPIPSWeightsMissing, weights_file

        try:
            weights_file(net)
        except LPIPSWeightsMissing as exc:
            return str(exc)
        return None

    return check


class _LPIPSMetric(Metric):
    higher_is_better = False
    net = "alex"

    def __init__(self, batch_size: int = 8) -> None:
        self.batch_size = batch_size
        self._model = None

    @torch.no_grad()
    def __call__(self, pred: Tensor, target: Tensor) -> Tensor:
        from framework.image.lpips import LPIPS

        self.check_images(pred, target)
        if self._model is None:
            self._model = LPIPS(self.net)
        self._model.to(pred.device)
        p = pred.permute(0, 3, 1, 2).float()  # [B, 3, H, W]
        t = target.permute(0, 3, 1, 2).float()
        chunks = [
            self._model(p[i : i + self.batch_size], t[i : i + self.batch_size], normalize=True)
            for i in range(0, p.shape[0], self.batch_size)
        ]
        return torch.cat(chunks) if chunks else p.new_zeros(0)


@register("metric", "lpips_alex", requires=_requires("alex"))
class LPIPSAlex(_LPIPSMetric):
    net = "alex"


@register("metric", "lpips_vgg", requires=_requires("vgg"))
class LPIPSVGG(_LPIPSMetric):
    net = "vgg"

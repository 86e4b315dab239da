"""Dataset `zju_mocap`: sequences in the ZJU-MoCap / Neural Body layout, with the published protocols.

The dataset itself is `framework.data.zju.dataset.ZjuMocapDataset` (the synthetic studio reads through it too); this
module only registers it under its config name.
"""

from framework.data.zju.dataset import ZjuMocapDataset
from framework.registry import register

__all__ = ["ZjuMocapDataset"]

register("dataset", "zju_mocap")(ZjuMocapDataset)

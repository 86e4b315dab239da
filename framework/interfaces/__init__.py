"""One small abstract base class per component kind, with the behaviour every implementation shares (a body's
kinematics, a metric's input check, the `execution` a component runs with). Imports `rig`, `splat` and core only."""

from framework.interfaces.body import BodyModel
from framework.interfaces.corrector import Corrector
from framework.interfaces.dataset import MultiViewDataset
from framework.interfaces.deformer import Deformer, DeformOutput
from framework.interfaces.densifier import Densifier
from framework.interfaces.loss import Loss
from framework.interfaces.metric import Metric
from framework.interfaces.rasterizer import Rasterizer

__all__ = [
    "BodyModel",
    "Corrector",
    "Deformer",
    "DeformOutput",
    "Densifier",
    "Loss",
    "Metric",
    "MultiViewDataset",
    "Rasterizer",
]

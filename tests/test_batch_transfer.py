"""Training batches reach a GPU without the host waiting: the DataLoader pins them (`FrameBatch.pin_memory`, every
tensor and the cameras'), and the data module moves them with `non_blocking` to CUDA only. A CPU cannot pin memory, so
the CPU tests record the calls; the gpu test moves a pinned batch for real and compares the values."""

from __future__ import annotations

import pytest
import torch

from framework.lightning.data import FrameDataModule
from framework.types import Cameras, FrameBatch

NEEDS_CUDA = {"condition": not torch.cuda.is_available(), "reason": "needs a CUDA device"}


def _batch() -> FrameBatch:
    g = torch.Generator().manual_seed(0)
    cams = Cameras(torch.rand(1, 3, 3, generator=g), torch.rand(1, 4, 4, generator=g), 6, 5)
    return FrameBatch(
        image=torch.rand(1, 5, 6, 3, generator=g),
        mask=torch.rand(1, 5, 6, generator=g),
        boundary=torch.rand(1, 5, 6, generator=g),
        cameras=cams,
        frame=torch.tensor([3]),
        pose=torch.rand(1, 4, 3, generator=g),
        root=None,
    )


def _tensors(batch: FrameBatch) -> list[torch.Tensor]:
    fields = (
        batch.image,
        batch.mask,
        batch.boundary,
        batch.frame,
        batch.pose,
        batch.cameras.K,
        batch.cameras.world_to_cam,
    )
    return [t for t in fields if t is not None]


def test_pin_memory_pins_every_tensor_and_keeps_the_values(monkeypatch) -> None:
    batch, pinned = _batch(), []

    def pin(t: torch.Tensor) -> torch.Tensor:
        pinned.append(t)
        return t.clone()

    monkeypatch.setattr(torch.Tensor, "pin_memory", pin)
    out = batch.pin_memory()
    assert len(pinned) == len(_tensors(batch)) == 7 and out.root is None
    for a, b in zip(_tensors(out), _tensors(batch), strict=True):
        assert torch.equal(a, b)
    assert (out.cameras.width, out.cameras.height) == (6, 5)


@pytest.mark.parametrize(("device", "expected"), [("cuda", True), ("cpu", False)])
def test_module_moves_batches_non_blocking_to_cuda_only(monkeypatch, device: str, expected: bool) -> None:
    calls = []
    monkeypatch.setattr(FrameBatch, "to", lambda self, dev, non_blocking=False: calls.append((dev, non_blocking)))
    FrameDataModule.transfer_batch_to_device(object(), _batch(), torch.device(device), 0)  # FrameBatch: no super()
    assert calls == [(torch.device(device), expected)]


def test_non_blocking_reaches_every_tensor(monkeypatch) -> None:
    flags = []
    original = torch.Tensor.to

    def to(t, *args, **kwargs):
        flags.append(kwargs.get("non_blocking"))
        return original(t, *args, **kwargs)

    monkeypatch.setattr(torch.Tensor, "to", to)
    moved = _batch().to("meta", non_blocking=True)
    assert flags == [True] * 7 and moved.image.device.type == "meta"


@pytest.mark.gpu
@pytest.mark.skipif(**NEEDS_CUDA)
def test_pinned_batch_arrives_on_the_gpu_unchanged() -> None:
    batch = _batch()
    moved = batch.pin_memory().to(torch.device("cuda"), non_blocking=True)
    torch.cuda.synchronize()
    for a, b in zip(_tensors(moved), _tensors(batch), strict=True):
        assert a.is_cuda and torch.equal(a.cpu(), b)

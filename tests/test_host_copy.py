"""Values copied to the host without a wait: equal to the device's values once ready (`-m gpu`: on CUDA, from pinned
memory behind queued work), and the progress bar shows a refresh's loss and PSNR once they have landed."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from framework.lightning.callbacks import StepProgressBar
from framework.lightning.host_copy import HostCopy

NEEDS_CUDA = {"condition": not torch.cuda.is_available(), "reason": "needs a CUDA device"}
DEVICES = pytest.mark.parametrize(
    "device", ["cpu", pytest.param("cuda", marks=[pytest.mark.gpu, pytest.mark.skipif(**NEEDS_CUDA)])]
)


@DEVICES
def test_copies_equal_the_device_values_once_landed(device):
    x = torch.randn(1000, 1000, device=device)
    y = (x @ x).sum()  # queued work the copy must come after
    flag = ~torch.isfinite(y)
    copy = HostCopy([y, flag])
    if device == "cpu":
        assert copy.ready()
    copy.wait()
    assert copy.ready()
    host_y, host_flag = copy.values()
    assert host_y.device.type == "cpu" and host_y.is_pinned() == (device == "cuda")
    assert float(host_y.numpy()) == float(y) and bool(host_flag.numpy()) == bool(flag)


@DEVICES
def test_progress_bar_shows_each_refresh_once_it_has_landed(device):
    bar = StepProgressBar(refresh_every=10)
    trainer = SimpleNamespace(max_steps=40, global_step=0)
    module = SimpleNamespace(avatar=SimpleNamespace(gaussians=SimpleNamespace(num=123)), last_train_psnr=None)
    bar.on_train_start(trainer, module)
    shown = []
    for step in (10, 20, 30):
        if device == "cuda":
            torch.cuda.synchronize()  # the previous refresh's copy has landed; this one's may not have yet
        trainer.global_step = step
        module.last_train_psnr = torch.tensor(20.0 + step, device=device)
        bar.on_train_batch_end(trainer, module, {"loss": torch.tensor(step / 100, device=device)}, None, 0)
        shown.append(dict(kv.split("=") for kv in bar.bar.postfix.split(", ")) if bar.bar.postfix else {})
    bar.on_train_end(trainer, module)
    if device == "cpu":  # ready at once: every refresh shows its own values
        assert shown == [{"loss": f"{s / 100:.4f}", "psnr": f"{20 + s:.2f}", "n": "123"} for s in (10, 20, 30)]
    else:  # this refresh's values, or the previous one's
        for i, step in enumerate((20, 30), start=1):
            allowed = {(f"{s / 100:.4f}", f"{20 + s:.2f}") for s in (step - 10, step)}
            assert (shown[i]["loss"], shown[i]["psnr"]) in allowed

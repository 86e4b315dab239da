"""tools/bench_train.py's section clock: with a device synchronisation, the time of work a section queued is charged
to that section, not to the section in which the host happens to wait."""

from __future__ import annotations

import time

import pytest
import torch
from tool_module import load_tool


class FakeDevice:
    """Queued work that only finishes when the host synchronises (as CUDA kernels after their launch returns)."""

    def __init__(self) -> None:
        self.pending = 0.0
        self.syncs = 0

    def queue(self, seconds: float) -> None:
        self.pending += seconds

    def synchronize(self) -> None:
        self.syncs += 1
        time.sleep(self.pending)
        self.pending = 0.0


@pytest.mark.parametrize("synchronised", [True, False])
def test_queued_work_is_charged_to_the_section_that_queued_it_when_synchronised(synchronised: bool) -> None:
    tool = load_tool("bench_train")
    device = FakeDevice()
    clock = tool.Clock()
    if synchronised:
        clock.device_sync = device.synchronize
    clock.push("render")
    device.queue(0.05)  # launched here, runs later
    clock.pop()
    clock.push("loss")
    if not synchronised:
        device.synchronize()  # the host waits here (an .item(), say)
    clock.pop()
    wall, _ = clock.take()
    render, loss = wall.get("render", 0.0), wall.get("loss", 0.0)
    if synchronised:
        assert render >= 0.05 and loss < 0.02
    else:
        assert render < 0.02 and loss >= 0.05


def test_sections_synchronise_only_on_cuda_unless_switched_off() -> None:
    tool = load_tool("bench_train")
    assert tool.device_sync_for(torch.device("cpu"), "auto") is None
    assert tool.device_sync_for(torch.device("cpu"), "on") is None
    assert tool.device_sync_for(torch.device("cuda", 0), "off") is None
    assert tool.device_sync_for(torch.device("cuda", 0), "auto") is torch.cuda.synchronize
    with pytest.raises(ValueError, match="sections-sync"):
        tool.device_sync_for(torch.device("cpu"), "always")

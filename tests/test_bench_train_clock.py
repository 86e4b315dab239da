"""tools/bench_train.py's section clock: with a device synchronisation, the time of work a section queued is charged
to that section, not to the section in which the host happens to wait."""

from __future__ import annotations

import pytest
import torch
from tool_module import load_tool


class FakeTime:
    """The tool's clock on simulated time, so the test does not depend on how busy the machine is."""

    def __init__(self) -> None:
        self.now = 0.0

    def perf_counter(self) -> float:
        return self.now

    def process_time(self) -> float:
        return 0.0


class FakeDevice:
    """Queued work that only finishes when the host synchronises (as CUDA kernels after their launch returns)."""

    def __init__(self, clock: FakeTime) -> None:
        self.clock = clock
        self.pending = 0.0
        self.syncs = 0

    def queue(self, seconds: float) -> None:
        self.pending += seconds

    def synchronize(self) -> None:
        self.syncs += 1
        self.clock.now += self.pending
        self.pending = 0.0


@pytest.mark.parametrize("synchronised", [True, False])
def test_queued_work_is_charged_to_the_section_that_queued_it_when_synchronised(synchronised, monkeypatch) -> None:
    tool = load_tool("bench_train")
    fake_time = FakeTime()
    monkeypatch.setattr(tool, "time", fake_time)
    device = FakeDevice(fake_time)
    clock = tool.Clock()
    if synchronised:
        clock.device_sync = device.synchronize
    clock.push("render")
    device.queue(0.05)  # launched here, runs later
    fake_time.now += 0.001  # the launch itself
    clock.pop()
    clock.push("loss")
    if not synchronised:
        device.synchronize()  # the host waits here (an .item(), say)
    clock.pop()
    wall, _ = clock.take()
    render, loss = wall.get("render", 0.0), wall.get("loss", 0.0)
    if synchronised:
        assert render == pytest.approx(0.051) and loss == 0.0
    else:
        assert render == pytest.approx(0.001) and loss == pytest.approx(0.05)


def test_sections_synchronise_only_on_cuda_unless_switched_off() -> None:
    tool = load_tool("bench_train")
    assert tool.device_sync_for(torch.device("cpu"), "auto") is None
    assert tool.device_sync_for(torch.device("cpu"), "on") is None
    assert tool.device_sync_for(torch.device("cuda", 0), "off") is None
    assert tool.device_sync_for(torch.device("cuda", 0), "auto") is torch.cuda.synchronize
    with pytest.raises(ValueError, match="sections-sync"):
        tool.device_sync_for(torch.device("cpu"), "always")


def test_cores_ceiling_matches_a_hand_computed_step() -> None:
    """Three rows: a serial 10 ms row, a 2-thread 20 ms row (36 ms CPU) and a 5 ms row at 1.1 cores. On 2 threads
    the two single-core rows would take 10/2 and 5.5/2 ms: (10 + 36 + 5.5) / (5 + 20 + 2.75) = 51.5 / 27.75."""
    tool = load_tool("bench_train")
    summary = {
        "rows": {
            "glue": {"mean_ms": 10.0, "cpu_mean_ms": 10.0},
            "backward": {"mean_ms": 20.0, "cpu_mean_ms": 36.0},
            "optimizer": {"mean_ms": 5.0, "cpu_mean_ms": 5.5},
        }
    }
    c = tool.cores_ceiling(summary, threads=2)
    assert c["single_core_rows"] == ["glue", "optimizer"]
    assert c["single_core_ms"] == pytest.approx(15.0)
    assert c["cores"] == pytest.approx(51.5 / 35.0)
    assert c["ceiling"] == pytest.approx(51.5 / 27.75)
    # one thread: nothing to gain, the ceiling is the measured figure
    assert tool.cores_ceiling(summary, threads=1)["ceiling"] == pytest.approx(51.5 / 35.0)

"""The training step's small work (losses, optimizer, checks, densifier bookkeeping) runs on `small_work_threads`
CPU threads, the render and the backward on all of them (framework.runtime.cpu_threads)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from test_training import _train

from framework.runtime import cpu_threads


@pytest.fixture
def two_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def test_the_block_runs_on_the_given_threads_and_restores_them(two_threads) -> None:
    cpu = torch.device("cpu")
    with cpu_threads(1, cpu):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2
    with pytest.raises(RuntimeError), cpu_threads(1, cpu):
        raise RuntimeError("inside")
    assert torch.get_num_threads() == 2  # restored on the way out of an error too


@pytest.mark.parametrize(
    ("threads", "device"),
    [(None, "cpu"), (2, "cpu"), (8, "cpu"), (1, "meta")],  # no limit, not fewer, more, another device
)
def test_the_block_changes_nothing_unless_it_lowers_a_cpu_count(two_threads, threads, device) -> None:
    with cpu_threads(threads, torch.device(device)):
        assert torch.get_num_threads() == 2


def test_a_training_step_runs_its_small_work_on_one_thread_and_its_backward_on_all(tmp_path: Path) -> None:
    log = tmp_path / "threads.txt"
    proc = _train(
        tmp_path,
        "trainer.max_steps=3",
        "threads=2",
        "small_work_threads=1",
        f"+loss.terms.probe={{name: thread_probe, weight: 1.0, log: '{log}'}}",
        faults={},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    moments = log.read_text().split("\n")[:-1]
    train = moments[: 3 * 3]  # three steps of loss, backward, optimizer (validation runs no backward)
    assert train == ["loss 1", "backward 2", "optimizer 1"] * 3, moments

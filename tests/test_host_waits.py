"""_bench.host_waits: which aten calls queue device work (a kernel or a copy) and which are views or bare
allocations, counted against a hand count of small programs whose kernels are known."""

from __future__ import annotations

import pytest
import torch
from _bench.host_waits import OperatorCount, cuda_device_events


def _count(fn) -> OperatorCount:
    counter = OperatorCount()
    with counter:
        fn()
    return counter


X = torch.randn(4, 6)

# Each program alone, so that the test holds whatever aten operators a torch version decomposes it into: a view or an
# allocation queues nothing however many aten calls it takes; an arithmetic operator queues at least one kernel.
VIEWS_AND_ALLOCATIONS = {
    "view": lambda: X.view(2, 12),
    "unsqueeze": lambda: X.unsqueeze(0),
    "transpose": lambda: X.t(),
    "detach": lambda: X.detach(),
    "select and slice": lambda: X[0, 1:],
    "expand": lambda: X[:1].expand(3, 6),
    "unbind": lambda: X.unbind(0),
    "empty": lambda: torch.empty(5),
    "empty_like": lambda: torch.empty_like(X),
}
DEVICE_WORK = {
    "mul": lambda: X * 2,
    "add": lambda: X + 1,
    "sum": lambda: X.sum(),
    "contiguous copy": lambda: X.t().contiguous(),
    "zeros": lambda: torch.zeros(3),
}


@pytest.mark.parametrize("name", VIEWS_AND_ALLOCATIONS)
def test_views_and_allocations_issue_no_device_work(name: str) -> None:
    counter = _count(VIEWS_AND_ALLOCATIONS[name])
    assert counter.operators >= 1, "the counter saw no operator at all"
    assert counter.launches == 0 and counter.waits == 0, (counter.launches, counter.waits)


@pytest.mark.parametrize("name", DEVICE_WORK)
def test_arithmetic_reductions_and_copies_queue_device_work(name: str) -> None:
    counter = _count(DEVICE_WORK[name])
    assert counter.launches >= 1 and counter.waits == 0, (counter.launches, counter.waits)


@pytest.mark.parametrize("program", [lambda: float(X.sum()), lambda: torch.tensor([1.0, 2.0])])
def test_a_value_crossing_between_host_and_device_is_one_wait(program) -> None:
    """The host reads a value (`float`), or a tensor is made from Python values: a copy, and one wait."""
    counter = _count(program)
    assert counter.waits == 1 and counter.launches >= 1, (counter.waits, counter.launches)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the answer without a CUDA device")
def test_device_events_are_none_without_cuda() -> None:
    """Not measured is None, never a zero."""
    assert cuda_device_events(lambda: torch.randn(3) * 2) is None


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_device_events_count_eager_kernels_and_a_compiled_fusion() -> None:
    """Eager: one kernel per element-wise operator. Compiled: Triton fuses the chain into one kernel, which the
    dispatch-mode counter cannot see (under it dynamo runs the function eagerly)."""
    x = torch.randn(1000, device="cuda")

    def chain(t: torch.Tensor) -> torch.Tensor:
        return ((t * 2 + 1).relu() - 3).abs()

    assert cuda_device_events(lambda: chain(x)) == 5  # mul, add, relu, sub, abs
    compiled = torch.compile(chain)
    compiled(x)  # compiles
    assert cuda_device_events(lambda: compiled(x)) == 1
    counter = OperatorCount()
    with counter:
        compiled(x)
    assert counter.launches == 5  # the eager operators: what the counter sees

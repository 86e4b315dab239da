"""framework.host_waits: which aten calls queue device work (a kernel or a copy) and which are views or bare
allocations, counted against a hand count of small programs whose kernels are known."""

from __future__ import annotations

import pytest
import torch

from framework.host_waits import OperatorCount, cuda_device_events


def _count(fn) -> OperatorCount:
    counter = OperatorCount()
    with counter:
        fn()
    return counter


def test_views_and_allocations_issue_no_device_work() -> None:
    x = torch.randn(4, 6)

    def views() -> None:
        y = x.view(2, 12).unsqueeze(0).squeeze(0).t()  # view, unsqueeze, squeeze, t
        y.detach()[0, 1:].expand(3, 11)  # detach, select, slice, expand
        x.unbind(0)  # unbind
        torch.empty(5)  # an allocation
        torch.empty_like(x)  # an allocation

    counter = _count(views)
    assert counter.operators == 4 + 4 + 1 + 2, counter.operators
    assert counter.launches == 0 and counter.waits == 0


def test_arithmetic_reductions_and_waits_queue_device_work() -> None:
    x = torch.randn(4, 6)

    def work() -> None:
        y = x * 2 + 1  # mul, add: two kernels
        s = y.sum()  # one reduction
        y.t().contiguous()  # t (a view), then clone: one copy kernel
        torch.zeros(3)  # zeros: a fill kernel
        float(s)  # the host reads a value: a copy, and a wait
        torch.tensor([1.0, 2.0])  # made from Python values: a copy, and a wait

    counter = _count(work)
    assert counter.waits == 2, counter.waits
    assert counter.launches == 2 + 1 + 1 + 1 + 2, counter.launches
    assert counter.operators - counter.launches >= 1  # the t() view at least


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

"""framework.host_waits: which aten calls queue device work (a kernel or a copy) and which are views or bare
allocations, counted against a hand count of small programs whose kernels are known."""

from __future__ import annotations

import torch

from framework.host_waits import OperatorCount


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

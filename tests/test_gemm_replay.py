"""The matrix products `bench_train` replays as the MLPs' GEMM floor: every product of a forward and backward is
recorded, with its shapes, and the count and FLOPs match the closed form of a dense MLP."""

from __future__ import annotations

import torch
from _bench.gemm_rate import record_gemms, replay_gemms
from torch import nn


def test_an_mlp_forward_backward_records_its_three_products_per_layer() -> None:
    rows, dims = 300, [27, 32, 32, 22]
    torch.manual_seed(0)
    mlp = nn.Sequential(nn.Linear(27, 32), nn.ReLU(), nn.Linear(32, 32), nn.ReLU(), nn.Linear(32, 22))
    x = torch.randn(rows, dims[0], requires_grad=True)

    calls = record_gemms(lambda: mlp(x).square().sum().backward())

    # closed form: per layer a -> b, the forward X W^T, the weight gradient G^T X, the input gradient G W
    per_layer = [2 * rows * a * b for a, b in zip(dims[:-1], dims[1:], strict=True)]
    assert len(calls) == 3 * len(per_layer)
    assert sum(c.flops for c in calls) == 3 * sum(per_layer)
    shapes = sorted(tuple(o[0] for o in c.operands[-2:]) for c in calls)
    assert ((rows, 27), (27, 32)) in shapes  # the first layer's forward product
    assert ((32, rows), (rows, 27)) in shapes  # its weight gradient, over the rows


def test_a_frozen_input_records_no_input_gradient_of_the_first_layer() -> None:
    mlp = nn.Linear(9, 16)
    x = torch.randn(50, 9)  # no gradient wanted: autograd skips the product for it
    calls = record_gemms(lambda: mlp(x).sum().backward())
    assert len(calls) == 2
    assert sum(c.flops for c in calls) == 2 * (2 * 50 * 9 * 16)


def test_replay_runs_the_recorded_products_and_times_each_pass() -> None:
    a, b = torch.randn(64, 8), torch.randn(8, 5)
    calls = record_gemms(lambda: (a @ b, torch.addmm(torch.zeros(5), a, b, beta=0.5), torch.bmm(a[None], b[None])))
    aten = torch.ops.aten
    assert [c.op for c in calls] == [aten.mm.default, aten.addmm.default, aten.bmm.default]
    assert calls[1].scalars == {"beta": 0.5}
    times = replay_gemms(calls, repeats=3, device="cpu")
    assert len(times) == 3 and all(t > 0 for t in times)

"""tools/count_syncs.py's counter: each operator that makes a GPU host wait is counted once per call, at the line of
our code that made it, and nothing else is counted."""

from __future__ import annotations

from collections import Counter

import torch
from tool_module import load_tool


def test_counter_counts_each_sync_once_and_nothing_else() -> None:
    tool = load_tool("count_syncs")
    from framework.rig.polar import polar_rotation_values

    counter = tool.SyncCounter()
    counter.step = 0
    x = torch.randn(50, 3)
    mask = x[:, 0] > 0
    with counter:
        y = (x * 2 + 1).sum(0).exp()  # no sync: arithmetic and reductions stay on the device
        float(y[0])  # 1 item
        x[mask]  # 1 boolean index
        torch.nonzero(mask)  # 1 nonzero
        torch.repeat_interleave(torch.tensor([1, 2]))  # 1 repeat_interleave (no output size)
        torch.repeat_interleave(torch.tensor([1, 2]), output_size=3)  # none: the size is given
        x.to("meta")  # 1 host-to-device copy (the meta device stands in for a GPU)
        x.to("meta", non_blocking=True)  # none: the host does not wait
        torch.empty(50, 3, device="meta").copy_(x)  # 1 host-to-device copy
        A = torch.eye(3).expand(4, 3, 3) + 0.01 * torch.randn(4, 3, 3)
        polar_rotation_values(A)  # well-conditioned: one check, then the Newton loop's own
        counter.step = None
        float(y[1])  # outside a counted step
    by_kind: Counter[str] = Counter()
    for (kind, _site), c in counter.counts.items():
        by_kind[kind] += c
    assert by_kind["boolean index"] == 1 and by_kind["nonzero"] == 1 and by_kind["repeat_interleave"] == 1
    assert by_kind["tensor from Python values (host-to-device copy)"] == 2  # the two torch.tensor([1, 2])
    assert by_kind["host-to-device copy (.to)"] == 2
    polar_sites = {s: c for (k, s), c in counter.counts.items() if "framework/rig/polar.py" in s}
    newton = sum(c for s, c in polar_sites.items() if "_rotation_newton" in s)
    entry = sum(c for s, c in polar_sites.items() if "_polar_values_entry_major" in s)
    assert entry == 1 and newton >= 1  # the all-good test is the only sync before the loop
    assert by_kind["item / float / bool"] == 1 + entry + newton  # float(y[0]); float(y[1]) was not counted


def test_counter_tells_launches_from_views() -> None:
    """A view is an operator the host dispatches but no launch; arithmetic is both (_bench.host_waits)."""
    tool = load_tool("count_syncs")
    counter = tool.SyncCounter()
    counter.step = 0
    x = torch.randn(6, 4)
    with counter:
        (x.view(-1).unsqueeze(0) * 2).sum()  # view, unsqueeze; mul, sum
    # at least: whatever aten calls a torch version makes of them, the two views launch nothing, mul and sum launch
    operators, launches = sum(counter.operators.values()), sum(counter.launches.values())
    assert operators - launches >= 2 and launches >= 2, (operators, launches)
    assert sum(counter.launch_sites.values()) == launches

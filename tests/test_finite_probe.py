"""`finite_probe` folds many tensors into one scalar that is finite exactly when every entry is: a NaN or an Inf in
any tensor (of any size, anywhere) makes it non-finite, None and empty tensors are skipped. On CUDA float32 tensors
it takes one multi-tensor kernel (`-m gpu` runs the same checks there)."""

from __future__ import annotations

import pytest
import torch

from framework.lightning.divergence import finite_probe

NEEDS_CUDA = {"condition": not torch.cuda.is_available(), "reason": "needs a CUDA device"}
ON_CUDA = pytest.param("cuda", marks=[pytest.mark.gpu, pytest.mark.skipif(**NEEDS_CUDA)])


@pytest.mark.parametrize("device", ["cpu", ON_CUDA])
def test_probe_is_non_finite_exactly_when_an_entry_is(device: str) -> None:
    g = torch.Generator().manual_seed(0)
    tensors = [torch.randn(n, generator=g).to(device) for n in (7, 3000, 1, 250)]
    assert bool(torch.isfinite(finite_probe([*tensors, None, torch.empty(0, device=device)])))
    for bad in (float("nan"), float("inf"), float("-inf")):
        for which in range(len(tensors)):
            broken = [t.clone() for t in tensors]
            broken[which][-1] = bad
            assert not bool(torch.isfinite(finite_probe(broken))), (bad, which)
    mixed = [tensors[0], tensors[1].double()]  # not all float32: the per-tensor sums
    assert bool(torch.isfinite(finite_probe(mixed)))
    assert finite_probe([]).item() == 0.0

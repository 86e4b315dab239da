"""`use_compiled_paths(False)` makes a CPU run the torch code an accelerator runs: every compiled path's test answers
no (each module imported `cpu_float` by name, so the switch must act inside it), and the SSIM then equals kornia's."""

from __future__ import annotations

import pytest
import torch

from framework.image import compiled_ssim
from framework.image.ssim import ssim_map
from framework.model import compiled_posenc, corrector_mlp, lbs_deformer
from framework.runtime import use_compiled_paths
from plugins.rasterizer import numba_cpu


def test_switch_turns_every_compiled_path_away_and_restores_it() -> None:
    x = torch.rand(1, 3, 24, 24)
    modules = (compiled_ssim, compiled_posenc, lbs_deformer, numba_cpu, corrector_mlp)
    assert all(m.cpu_float(x) for m in modules)
    previous = use_compiled_paths(False)
    try:
        assert previous is True
        assert not any(m.cpu_float(x) for m in modules)
        y = torch.rand(1, 3, 24, 24)
        # by default a CPU float image takes the compiled SSIM; switched off, kornia's path runs (equal bit for bit)
        default, kornia = ssim_map(x, y, 11), ssim_map(x, y, 11, compiled=False)
        torch.testing.assert_close(default, kornia, rtol=0, atol=0)
    finally:
        assert use_compiled_paths(previous) is False
    assert all(m.cpu_float(x) for m in modules)


def test_fused_corrector_layers_follow_the_switch() -> None:
    """F_a's oneDNN fused layers (CPU inference) are a compiled CPU path too: switched off, the plain layers run, as on
    a GPU."""
    if not corrector_mlp._FUSED_LINEAR_AVAILABLE:
        pytest.skip("this torch build has no oneDNN fused linear: the plain layers always run")
    x = torch.rand(8, 4)
    with torch.no_grad():
        assert corrector_mlp._fuses_layers(x)
        previous = use_compiled_paths(False)
        try:
            assert not corrector_mlp._fuses_layers(x)
        finally:
            use_compiled_paths(previous)
    assert not corrector_mlp._fuses_layers(x)  # gradients on: the plain layers (the fused op has no backward)

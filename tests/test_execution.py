"""How components run is chosen when the model is built (`framework.execution`), not by a process-wide switch: the
torch execution makes a CPU run the torch code an accelerator runs (no compiled kernel is called, and the D-SSIM then
equals kornia's bit for bit), the compiled one takes the kernels, and both can live in one process."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

import framework.kernels.posenc as kernel_posenc
import framework.kernels.ssim as kernel_ssim
from framework.build import ConfigError
from framework.execution import COMPILED, TORCH, Execution
from framework.image.ssim import ssim_map
from framework.model import corrector_mlp
from framework.model.posenc import posenc
from framework.plugins import load_plugins
from framework.registry import LOSSES, RASTERIZERS
from framework.types import Cameras, FrameBatch, RenderOutput

load_plugins()


def test_auto_resolves_against_the_device_and_bad_values_are_refused() -> None:
    assert Execution.resolve("auto", "cpu") == COMPILED
    assert Execution.resolve("auto", "cuda") == TORCH
    assert Execution.resolve("torch", "cpu") == TORCH and Execution.resolve("compiled", "cuda") == COMPILED
    # a checkpoint written before the `execution` node existed: tests/test_config_schema.py
    with pytest.raises(ValueError, match="execution.kernels"):
        Execution.resolve("gpu", "cpu")
    with pytest.raises(ValueError, match="execution.kernels"):
        Execution("auto")  # resolved objects only


def test_only_cpu_floats_under_the_compiled_execution_take_the_kernels() -> None:
    x = torch.rand(3, 4)
    assert COMPILED.compiled(x) and COMPILED.compiled(x.double(), x)
    assert not COMPILED.compiled(x.half()) and not COMPILED.compiled(x, x.half())
    assert not COMPILED.compiled(x.to(torch.device("meta")))
    assert not TORCH.compiled(x)


def test_the_config_check_names_a_bad_kernels_value() -> None:
    from framework.config_checks import check_train_config

    check_train_config(OmegaConf.create({"execution": {"kernels": "auto"}}))
    with pytest.raises(ConfigError, match="execution.kernels"):
        check_train_config(OmegaConf.create({"execution": {"kernels": "numba"}}))


def _forbid(monkeypatch, module, name: str) -> None:
    def called(*args, **kwargs):
        raise AssertionError(f"{module.__name__}.{name} called under the torch execution")

    monkeypatch.setattr(module, name, called)


def test_torch_execution_d_ssim_is_kornias_bit_for_bit_and_compiled_differs_by_rounding(monkeypatch) -> None:
    g = torch.Generator().manual_seed(0)
    rgb, image = torch.rand(1, 24, 24, 3, generator=g), torch.rand(1, 24, 24, 3, generator=g)
    batch = FrameBatch(image=image, mask=torch.ones(1, 24, 24), boundary=None, cameras=None, frame=None)
    render = RenderOutput(rgb=rgb, alpha=torch.ones(1, 24, 24, 1), depth=None, means2d=None, radii=None)
    compiled_loss = LOSSES.build("dssim")
    torch_loss = LOSSES.build("dssim")
    torch_loss.set_execution(TORCH)
    compiled_value = compiled_loss(render, batch, {})
    _forbid(monkeypatch, kernel_ssim, "ssim_map")
    value = torch_loss(render, batch, {})
    kornia = (1.0 - ssim_map(rgb.permute(0, 3, 1, 2), image.permute(0, 3, 1, 2), 11)).mean()
    torch.testing.assert_close(value, kornia, rtol=0, atol=0)
    torch.testing.assert_close(compiled_value, kornia, rtol=0, atol=1e-6)


def test_posenc_follows_the_execution_it_is_given(monkeypatch) -> None:
    x = torch.rand(50, 3) * 2 - 1
    compiled = posenc(x, 4, COMPILED)
    _forbid(monkeypatch, kernel_posenc, "posenc_compiled")
    torch.testing.assert_close(posenc(x, 4, TORCH), compiled, rtol=0, atol=1e-6)


def test_the_numba_rasterizer_under_the_torch_execution_is_torch_ref(monkeypatch) -> None:
    """No compiled loop runs; the image is torch_ref's bit for bit."""
    g = torch.Generator().manual_seed(1)
    n = 30
    means = torch.randn(n, 3, generator=g) * 0.3
    quats, scales = torch.randn(n, 4, generator=g), torch.rand(n, 3, generator=g) * 0.1 + 0.02
    opacities, sh = torch.rand(n, generator=g), torch.randn(n, 4, 3, generator=g) * 0.3
    w2c = torch.eye(4)
    w2c[2, 3] = 3.0
    cams = Cameras(torch.tensor([[[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]]]), w2c[None], 32, 32)
    numba = RASTERIZERS.build("numba")
    numba.set_execution(TORCH)
    reference = RASTERIZERS.build("torch_ref")
    reference.set_execution(TORCH)
    import framework.kernels.rasterize as kernel_rasterize

    _forbid(monkeypatch, kernel_rasterize, "project")
    with torch.no_grad():
        ours = numba.render(means, quats, scales, opacities, sh, cams, sh_degree=1)
        ref = reference.render(means, quats, scales, opacities, sh, cams, sh_degree=1)
    assert float(ours.alpha.amax()) > 0.1
    torch.testing.assert_close(ours.rgb, ref.rgb, rtol=0, atol=0)


def test_fused_corrector_layers_follow_the_execution() -> None:
    """F_a's oneDNN fused layers (CPU inference) are a CPU form too: under the torch execution the plain layers run,
    as on a GPU."""
    if not corrector_mlp._FUSED_LINEAR_AVAILABLE:
        pytest.skip("this torch build has no oneDNN fused linear: the plain layers always run")
    x = torch.rand(8, 4)
    with torch.no_grad():
        assert corrector_mlp._fuses_layers(x, COMPILED)
        assert not corrector_mlp._fuses_layers(x, TORCH)
    assert not corrector_mlp._fuses_layers(x, COMPILED)  # gradients on: the plain layers (the fused op has no backward)


def test_no_process_wide_switch_is_left() -> None:
    import framework.runtime as runtime

    assert not hasattr(runtime, "use_compiled_paths") and not hasattr(runtime, "cpu_float")

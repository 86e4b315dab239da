"""The conformance suite run on `torch_ref` forced to float32, a CPU stand-in for a float32-only backend such as gsplat.

It checks the suite's own float32 handling (`supports_float64 = False`: float32 finite-difference steps and
tolerances) and that every other check of the suite can be met in float32, so a failure on the GPU run points at the
backend, not at the suite. The backend is built here rather than registered, so no other test sees it.
"""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from framework.testing.conformance import *  # noqa: F401,F403
from framework.testing.conformance import make_random_scene, render_scene
from framework.types import Cameras, RenderOutput
from plugins.rasterizer.torch_ref import TorchRefRasterizer


class Float32TorchRef(TorchRefRasterizer):
    """torch_ref computing in float32 whatever it is given and casting back, as gsplat does."""

    supports_float64 = False

    def render(
        self,
        means: Tensor,
        quats: Tensor,
        scales: Tensor,
        opacities: Tensor,
        sh: Tensor,
        cameras: Cameras,
        *,
        sh_degree: int,
        background: Tensor | None = None,
        **planes: float,
    ) -> RenderOutput:
        dtype = means.dtype
        ts = [t.float() for t in (means, quats, scales, opacities, sh)]
        bg = None if background is None else background.float()
        out = super().render(*ts, cameras.to(means.device, torch.float32), sh_degree=sh_degree, background=bg, **planes)
        return RenderOutput(out.rgb.to(dtype), out.alpha.to(dtype), out.depth.to(dtype), out.means2d, out.radii)


@pytest.fixture(params=["torch_ref_float32"])
def backend_name(request: pytest.FixtureRequest) -> str:
    return request.param


@pytest.fixture
def backend(backend_name: str) -> Float32TorchRef:
    return Float32TorchRef()


def test_float64_inputs_are_computed_in_float32() -> None:
    """The stand-in really is float32-only: float64 inputs give torch_ref's float32 result, cast back."""
    out = render_scene(Float32TorchRef(), make_random_scene(0, 10, 12, 10, dtype=torch.float64))
    ref = render_scene(TorchRefRasterizer(), make_random_scene(0, 10, 12, 10, dtype=torch.float32))
    assert out.rgb.dtype == torch.float64
    torch.testing.assert_close(out.rgb, ref.rgb.double(), atol=0, rtol=0)

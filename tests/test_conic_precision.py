"""The conformance suite's allowance for conics inverted from a float32 screen covariance (gsplat's), checked on a CPU.

gsplat 1.5.3 forms each conic as 1 / (a c - b^2) of its float32 screen covariance. On an H200 that made the suite's
extreme scenes fail for a 148:1 needle across the image (screen condition number kappa ~ 2e4): alpha off by 3.9e-4,
the means' gradient by 2.1e-3 relative, where torch_ref, which forms the determinant without the cancellation, is
within 7e-8. Here a CPU backend makes the same error: torch_ref's render with its conics replaced by gsplat's, computed
by `_project_as_gsplat` (the projection kernel's float32 operations in its order, each one exactly rounded, so the
conics have the same bits on every CPU whatever kernels torch and numba pick there). The verdicts below are therefore
not knife edges: on the needles the emulation's error is 1.4-49 times the plain tolerance and at most 0.8 of the
allowance, and ten times the cancellation is 1.1-17 times the allowance. It shows that
- the error is real and a property of that conic: the emulation fails the suite's plain tolerances on a needle where
  torch_ref passes them;
- `conic_from_float32_covariance` (`framework.testing.conformance.extreme_tolerances`) admits it, on that needle and on
  the suite's hypothesis-drawn extreme scenes;
- the widened tolerance still catches a conic error ten times larger than the cancellation makes.
"""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from framework.geometry import quat_multiply, quat_normalize
from framework.interfaces.rasterizer import EPS2D
from framework.splat.projection import Projection
from framework.testing.conformance import (
    Scene,
    check_extreme_scene,
    extreme_camera,
    screen_condition_number,
    test_extremes_match_float64_reference,  # noqa: F401  (collected here: run on the emulation below)
)
from plugins.rasterizer.torch_ref import TorchRefRasterizer
from tests.test_gsplat_backend import _project_as_gsplat

F64 = torch.float64
EPS32 = torch.finfo(torch.float32).eps


class GsplatConic(TorchRefRasterizer):
    """torch_ref with gsplat 1.5.3's conics. `conic_error`, a relative error put on every conic, checks that the
    tolerance still catches what the cancellation does not explain."""

    conic_from_float32_covariance = True

    def __init__(self, conic_error: float = 0.0) -> None:
        super().__init__()
        self.conic_error = conic_error

    def project(self, means, quats, scales, opacities, K, world_to_cam, width, height, near, far) -> Projection:
        p = super().project(means, quats, scales, opacities, K, world_to_cam, width, height, near, far)
        quats = quat_normalize(quats)  # the wrapper hands gsplat guarded unit quaternions, as torch_ref uses them

        def conics_of(scales_in: torch.Tensor) -> torch.Tensor:  # [C, N, 3]
            *_, conics = _project_as_gsplat(
                means, quats, scales_in, opacities, world_to_cam, K, width, height, near, far, EPS2D
            )
            return conics

        with torch.no_grad():
            conics = conics_of(scales)
            ok = p.valid & (conics[..., 0] > 0) & torch.isfinite(conics).all(-1)  # gsplat culls det <= 0
        # again with unit scales for rows no camera draws (they keep torch_ref's conic), so that no NaN of theirs
        # reaches the gradients through `where`
        conics = conics_of(torch.where(ok.any(0).unsqueeze(-1), scales, torch.ones_like(scales)))
        conics = conics * (1.0 + self.conic_error)
        return replace(p, conics=torch.where(ok.unsqueeze(-1), conics, p.conics), valid=ok)


def needle(depth: float, short: float, tilt: float) -> Scene:
    """One Gaussian of scales (short, 148.4, short) m at `depth` m on the optical axis, its long axis turned onto the
    16 x 12 image's diagonal and tilted by `tilt` rad out of the image plane."""
    spin = math.atan2(12, 16) - math.pi / 2
    about_z = torch.tensor([math.cos(spin / 2), 0.0, 0.0, math.sin(spin / 2)], dtype=F64)
    about_x = torch.tensor([math.cos(tilt / 2), math.sin(tilt / 2), 0.0, 0.0], dtype=F64)
    sh = 0.5 * torch.randn(1, 1, 3, generator=torch.Generator().manual_seed(0), dtype=F64)
    return Scene(
        torch.tensor([[0.0, 0.0, depth]], dtype=F64),
        quat_multiply(about_z, about_x)[None],
        torch.tensor([[short, 148.4, short]], dtype=F64),
        torch.tensor([0.9], dtype=F64),
        sh,
        extreme_camera(),
        0,
    )


# (depth, short, tilt): the first like the H200's needle; the last has the largest gradient error of the 36 scanned
NEEDLES = [(2.0, 1.0, 0.0), (1.0, 0.5, 0.3), (2.0, 0.3, 0.0), (4.0, 0.3, 0.7)]


class _PlainTolerances(GsplatConic):
    conic_from_float32_covariance = False


@pytest.mark.parametrize("depth, short, tilt", NEEDLES)
def test_gsplat_conic_fails_the_plain_tolerance_where_torch_ref_passes(depth, short, tilt):
    scene = needle(depth, short, tilt)
    assert 1e4 < screen_condition_number(scene) < 1e6
    check_extreme_scene(TorchRefRasterizer(), "cpu", scene)
    with pytest.raises(AssertionError, match="condition number"):
        check_extreme_scene(_PlainTolerances(), "cpu", scene)
    check_extreme_scene(GsplatConic(), "cpu", scene)


@pytest.mark.parametrize("depth, short, tilt", NEEDLES)
def test_the_allowance_catches_ten_times_the_cancellation(depth, short, tilt):
    scene = needle(depth, short, tilt)
    error = 10 * screen_condition_number(scene) * EPS32
    with pytest.raises(AssertionError, match="condition number"):
        check_extreme_scene(GsplatConic(conic_error=error), "cpu", scene)


@pytest.fixture
def backend():
    """`test_extremes_match_float64_reference`, imported above, runs on the emulation."""
    return GsplatConic()


@pytest.fixture
def device():
    return "cpu"

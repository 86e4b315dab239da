"""The rasterizer contract: every backend renders the same function.

Semantics shared by all backends (the conformance suite in `framework.testing` checks them):
- Projection: p = R x + t (OpenCV). A Gaussian is culled (radius 0) when z <= near or z >= far.
- Covariance: Sigma = R S S^T R^T from the normalised quaternion (wxyz; a quaternion of norm <= 1e-12, zero
  included, counts as the identity: `framework.geometry.quat_normalize`) and scales; EWA splatting with the
  perspective Jacobian at the mean, where x/z and y/z are clamped to the field of view widened by 0.3 * tan(fov/2)
  on each side (as in 3DGS/gsplat); then 0.3 px^2 is added to the 2D covariance diagonal (low-pass filter).
- Pixel (i, j) has its centre at (j + 0.5, i + 0.5). For a pair (Gaussian g, pixel p):
  sigma = 0.5 * d^T Sigma2d^-1 d with d = mean2d - p; alpha = min(0.999, opacity * exp(-sigma));
  the pair contributes only if sigma >= 0 and alpha >= 1/255.
- Compositing: front to back by camera-space z. T starts at 1; for each contributing pair next_T = T * (1 - alpha);
  if next_T <= 1e-4 the pixel is finished and this pair is NOT added; otherwise the pair adds T * alpha * (colour, 1, z)
  and T = next_T. rgb = sum + T_final * background; alpha = 1 - T_final; depth = sum of T*alpha*z (not normalised).
- Colour: real SH up to `sh_degree` (3DGS constants) evaluated at the direction from the camera centre to the mean,
  plus 0.5, clamped at 0 from below.
- radii: ceil of the half-extent (pixels) of the screen box holding every pixel where alpha >= 1/255 could hold;
  0 for culled Gaussians (behind the camera, degenerate covariance, or the box entirely outside the image).
- means2d: projected centres [C, N, 2]; backends arrange for `.grad` to be populated by backward (densification).
  Rows of culled Gaussians hold finite values (no NaN or leftover memory); compare rows where radii > 0.
- Inputs: `check_render_inputs` (below) checks shapes with messages that name the argument; a backend calls it before
  handing tensors to a library whose own checks are bare assertions.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

from torch import Tensor

from framework.execution import ExecutionMixin

# The contract's numbers, defined once beside the splatting math that applies them (re-exported for backends).
from framework.splat.contract import (  # noqa: F401
    ALPHA_MAX,
    ALPHA_MIN,
    BOX_MARGIN,
    EPS2D,
    FAR_PLANE,
    LOG_T_MIN,
    NEAR_PLANE,
    TRANSMITTANCE_MIN,
)
from framework.types import BlendWeights, Cameras, RenderOutput


class Rasterizer(ExecutionMixin, ABC):
    """A differentiable Gaussian splatting backend."""

    #: Set by the registry decorator.
    registry_name: str = ""

    #: False for a backend that computes in float32 whatever it is given (float64 inputs are cast down and the
    #: results cast back, as gsplat's CUDA kernels do). The conformance suite then checks its gradients with
    #: float32-sized finite-difference steps and tolerances instead of float64 ones.
    supports_float64: bool = True

    #: True for a backend that forms each conic by inverting its float32 screen covariance, 1 / (a c - b^2), as
    #: gsplat's projection kernel does. For a covariance of condition number kappa that determinant cancels down to
    #: about kappa * eps32 relative accuracy, so a needle-thin Gaussian's opacity falloff is that far off in any such
    #: implementation. The conformance suite then widens its extreme-scene tolerances by that term
    #: (`framework.testing.conformance.extreme_tolerances`); everywhere else its checks are the same.
    conic_from_float32_covariance: bool = False

    @abstractmethod
    def render(
        self,
        means: Tensor,  # [N, 3] world positions
        quats: Tensor,  # [N, 4] wxyz, need not be normalised
        scales: Tensor,  # [N, 3] activated (positive) scales
        opacities: Tensor,  # [N] activated opacities in [0, 1]
        sh: Tensor,  # [N, K, 3] SH coefficients, K >= (sh_degree + 1) ** 2
        cameras: Cameras,
        *,
        sh_degree: int,
        background: Tensor | None = None,  # [3]; black when None
        near: float = NEAR_PLANE,
        far: float = FAR_PLANE,
    ) -> RenderOutput:
        """Render every camera; differentiable in all Gaussian tensors."""

    def blend_weights(
        self,
        means: Tensor,  # [N, 3]
        quats: Tensor,  # [N, 4]
        scales: Tensor,  # [N, 3]
        opacities: Tensor,  # [N]
        cameras: Cameras,
        *,
        near: float = NEAR_PLANE,
        far: float = FAR_PLANE,
    ) -> BlendWeights:
        """Per Gaussian, the blending weights T * alpha (as composited, after early termination) it has at the pixels
        of every camera: the largest, the sum of squares and the pair count; pruning removes Gaussians that never
        reach a threshold and ranks the others. Optional: a backend that cannot report them leaves this as is and
        callers fall back to `torch_ref`."""
        raise NotImplementedError(f"rasterizer '{self.registry_name}' does not report per-Gaussian blending weights")


def check_render_inputs(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, sh: Tensor, sh_degree: int
) -> None:
    """Shape checks with messages that name the argument, what was expected and what was found."""
    n = means.shape[0] if means.dim() == 2 else -1
    expected = {
        "means": (means, (n, 3)),
        "quats": (quats, (n, 4)),
        "scales": (scales, (n, 3)),
        "opacities": (opacities, (n,)),
    }
    if means.dim() != 2 or means.shape[1] != 3:
        raise ValueError(f"rasterizer input 'means': expected shape [N, 3], found {tuple(means.shape)}.")
    for name, (t, shape) in expected.items():
        if tuple(t.shape) != shape:
            raise ValueError(
                f"rasterizer input '{name}': expected shape {list(shape)} (N = {n} from means), found "
                f"{list(t.shape)}; pass one row per Gaussian (activated scales/opacities, wxyz quaternions)."
            )
    k = (sh_degree + 1) ** 2
    if sh.dim() != 3 or sh.shape[0] != n or sh.shape[2] != 3 or sh.shape[1] < k:
        raise ValueError(
            f"rasterizer input 'sh': expected shape [{n}, K >= {k}, 3] for sh_degree={sh_degree}, found "
            f"{list(sh.shape)}; lower sh_degree or allocate (sh_degree + 1)^2 coefficients."
        )

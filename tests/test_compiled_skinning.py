"""The compiled skinning (`framework.kernels.skinning`) against the torch skinning in float64, and the switch
that turns it on with the `numba` rasterizer."""

from __future__ import annotations

import math

import pytest
import torch

from framework.geometry import axis_angle_to_rotmat
from framework.kernels.skinning import lbs_with_sh_frames_compiled
from framework.rig.lbs import lbs_with_sh_frames
from framework.types import Gaussians

F64 = torch.float64
TOL = 1e-10  # both in float64: the polar iterations stop at different steps (per matrix here, per batch in torch)


def _gaussians(n: int, seed: int) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    return Gaussians(
        means=torch.randn(n, 3, generator=g, dtype=F64) * 0.5,
        quats=torch.randn(n, 4, generator=g, dtype=F64) * torch.rand(n, 1, generator=g, dtype=F64) * 3,
        log_scales=torch.randn(n, 3, generator=g, dtype=F64) - 3,
        opacity_logits=torch.randn(n, generator=g, dtype=F64),
        sh=torch.randn(n, 4, 3, generator=g, dtype=F64),
    )


def _transforms(j: int, seed: int, scale: float = 0.1) -> torch.Tensor:
    """[J, 4, 4] rigid bone transforms (rotations up to ~2.5 rad), times a per-bone uniform scale near 1."""
    g = torch.Generator().manual_seed(seed)
    T = torch.eye(4, dtype=F64).repeat(j, 1, 1)
    T[:, :3, :3] = axis_angle_to_rotmat(torch.randn(j, 3, generator=g, dtype=F64) * 1.5)
    T[:, :3, :3] *= 1 + scale * torch.rand(j, 1, 1, generator=g, dtype=F64)
    T[:, :3, 3] = torch.randn(j, 3, generator=g, dtype=F64)
    return T


def _weights(n: int, j: int, seed: int) -> torch.Tensor:
    """Sparse convex rows, as baked skinning weights are: 1-4 joints each, some rows rigid (one joint)."""
    g = torch.Generator().manual_seed(seed)
    w = torch.rand(n, j, generator=g, dtype=F64) ** 6
    w[torch.rand(n, j, generator=g) > 0.2] = 0
    w[torch.arange(n), torch.randint(j, (n,), generator=g)] += 0.3
    return w / w.sum(-1, keepdim=True)


@pytest.mark.parametrize("stretch", ["diag", "none"])
@pytest.mark.parametrize("centres", ["blended", "rigid"])
def test_matches_torch_skinning_in_float64(stretch: str, centres: str) -> None:
    g, w, T = _gaussians(500, 0), _weights(500, 22, 1), _transforms(22, 2)
    ref, R_ref = lbs_with_sh_frames(g, w, T, stretch, F64, centres)
    got, R = lbs_with_sh_frames_compiled(g, w, T, stretch, centres)
    for key in ("means", "quats", "log_scales"):
        torch.testing.assert_close(getattr(got, key), getattr(ref, key), atol=TOL, rtol=0, msg=key)
    torch.testing.assert_close(R, R_ref, atol=TOL, rtol=0)
    assert torch.equal(got.sh, g.sh) and torch.equal(got.opacity_logits, g.opacity_logits)


def test_reflections_and_zero_quaternions_match_torch() -> None:
    """det(A) < 0 with distinct singular values has one closest proper rotation (flip the smallest), found by the SVD
    in both; a quaternion of norm 0 is the identity in both."""
    g = _gaussians(4, 3)
    g.quats[0] = 0.0
    T = _transforms(2, 4, scale=0.0)
    T[1, :3, :3] = T[1, :3, :3] @ torch.diag(torch.tensor([1.2, 0.9, -0.5], dtype=F64))  # reflecting
    w = torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.3, 0.7], [0.5, 0.5]], dtype=F64)
    ref, R_ref = lbs_with_sh_frames(g, w, T, "diag", F64)
    got, R = lbs_with_sh_frames_compiled(g, w, T)
    torch.testing.assert_close(R, R_ref, atol=TOL, rtol=0)
    for key in ("means", "quats", "log_scales"):
        torch.testing.assert_close(getattr(got, key), getattr(ref, key), atol=TOL, rtol=0, msg=key)
    assert float(torch.linalg.det(R[1])) == pytest.approx(1.0)


def test_singular_and_non_finite_blends_stay_finite_rotations() -> None:
    """A 50/50 blend of antipodal rotations (rank 1) and all-zero weights (A = 0): the rotation is not determined
    there (the SVD's choice differs between libraries), but it is a proper rotation and every output is finite. A
    Gaussian on a non-finite bone gets the identity rotation, and only that Gaussian: the blend skips zero weights,
    where torch's product spreads NaN * 0 to every Gaussian."""
    g = _gaussians(3, 5)
    T = torch.eye(4, dtype=F64).repeat(3, 1, 1)
    T[1, :3, :3] = axis_angle_to_rotmat(torch.tensor([0.0, 0.0, math.pi], dtype=F64))
    T[2, 0, 0] = float("nan")
    w = torch.tensor([[0.5, 0.5, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    got, R = lbs_with_sh_frames_compiled(g, w, T)
    assert all(bool(torch.isfinite(t[:2]).all()) for t in (got.means, got.quats, got.log_scales, R))
    eye = torch.eye(3, dtype=F64).expand(3, 3, 3)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(3, dtype=F64), atol=1e-12, rtol=0)
    torch.testing.assert_close(R[2], torch.eye(3, dtype=F64))  # a non-finite blend -> the identity


def test_each_gaussian_is_posed_as_if_alone() -> None:
    """The polar iterations run 64 Gaussians side by side (`_polar_block`); a lane that has converged must keep its
    matrix while the others iterate. So every Gaussian's result is bit for bit the same whatever its block-mates: here
    the same Gaussians in reverse order and one at a time, mixing near-rigid blends (one or two steps) with strongly
    stretched ones (many steps), a reflection (the SVD) and a non-finite bone (the identity)."""
    n = 150
    g, w, T = _gaussians(n, 6), _weights(n, 6, 7), _transforms(6, 8, scale=2.0)
    T[2, :3, :3] = T[2, :3, :3] @ torch.diag(torch.tensor([1.5, 0.7, -0.4], dtype=F64))  # reflecting
    T[4, 1, 1] = float("inf")
    got, R = lbs_with_sh_frames_compiled(g, w, T)
    flip = torch.arange(n - 1, -1, -1)
    rev, R_rev = lbs_with_sh_frames_compiled(g.index(flip), w[flip], T)
    exact = {"rtol": 0.0, "atol": 0.0, "equal_nan": True}  # a Gaussian on the non-finite bone has NaN centres
    torch.testing.assert_close(R_rev, R[flip], **exact)
    for key in ("means", "quats", "log_scales"):
        torch.testing.assert_close(getattr(rev, key), getattr(got, key)[flip], **exact, msg=key)
    for i in (0, 1, 77, n - 1):
        one, R_one = lbs_with_sh_frames_compiled(g.index(torch.tensor([i])), w[i : i + 1], T)
        torch.testing.assert_close(R_one[0], R[i], **exact)
        torch.testing.assert_close(one.log_scales[0], got.log_scales[i], **exact)

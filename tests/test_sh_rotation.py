"""SH rotation: evaluating rotated coefficients at d equals evaluating the originals at R^T d (the renderer's basis)."""

from __future__ import annotations

import pytest
import torch

from framework.geometry import axis_angle_to_rotmat
from framework.rig.sh_rotation import rotate_sh
from framework.splat.sh import eval_sh

D64 = torch.float64


def random_rotations(n: int, seed: int, dtype=D64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return axis_angle_to_rotmat(torch.randn(n, 3, generator=g, dtype=dtype) * 2.0)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_rotated_evaluation_matches_rotated_direction(degree):
    g = torch.Generator().manual_seed(degree)
    n = 512
    sh = torch.randn(n, (degree + 1) ** 2, 3, generator=g, dtype=D64)
    R = random_rotations(n, 10 + degree)
    d = torch.randn(n, 3, generator=g, dtype=D64)
    got = eval_sh(degree, rotate_sh(sh, R), d)
    want = eval_sh(degree, sh, (R.mT @ d.unsqueeze(-1)).squeeze(-1))
    assert (got - want).abs().max() < 1e-10


def test_degree1_block_matches_closed_form():
    """The degree-1 block is a linear function v . d, so rotating it is rotating the vector v (closed form)."""
    R = random_rotations(64, 3)
    c = torch.zeros(64, 4, 1, dtype=D64)
    c[:, 1:, 0] = torch.randn(64, 3, dtype=D64)
    # f(d) = C1 * (c1 * -y + c2 * z + c3 * -x) = C1 * v . d with v = (-c3, -c1, c2)
    v = torch.stack([-c[:, 3, 0], -c[:, 1, 0], c[:, 2, 0]], dim=-1)
    v_rot = (R @ v.unsqueeze(-1)).squeeze(-1)  # f(R^T d) = v . R^T d = (R v) . d
    want = torch.stack([-v_rot[:, 1], v_rot[:, 2], -v_rot[:, 0]], dim=-1)
    assert torch.allclose(rotate_sh(c, R)[:, 1:, 0], want, atol=1e-12)


def test_composition_identity_and_dc():
    sh = torch.randn(32, 16, 3, dtype=D64)
    R1, R2 = random_rotations(32, 1), random_rotations(32, 2)
    assert torch.allclose(rotate_sh(rotate_sh(sh, R1), R2), rotate_sh(sh, R2 @ R1), atol=1e-10)
    assert torch.allclose(rotate_sh(sh, torch.eye(3, dtype=D64).expand(32, 3, 3)), sh, atol=1e-12)
    assert torch.equal(rotate_sh(sh, R1)[:, 0], sh[:, 0])
    # energy per degree is preserved (the rotation is orthogonal in this orthonormal basis)
    out = rotate_sh(sh, R1)
    for l in (1, 2, 3):
        lo, hi = l * l, (l + 1) ** 2
        assert torch.allclose(out[:, lo:hi].norm(dim=1), sh[:, lo:hi].norm(dim=1), atol=1e-10)


def test_shared_rotation_float32_half_and_empty():
    sh = torch.randn(100, 16, 3)
    R = random_rotations(1, 5, torch.float32)[0]
    d = torch.randn(100, 3)
    got = eval_sh(3, rotate_sh(sh, R), d)
    assert torch.allclose(got, eval_sh(3, sh, d @ R), atol=1e-4)  # R^T d as a row vector: d @ R
    half = rotate_sh(sh.half(), R.expand(100, 3, 3).half())
    assert half.dtype == torch.float16 and torch.isfinite(half).all()
    assert rotate_sh(torch.zeros(0, 16, 3), torch.zeros(0, 3, 3)).shape == (0, 16, 3)
    assert torch.equal(rotate_sh(sh[:, :1], R.expand(100, 3, 3)), sh[:, :1])
    with pytest.raises(ValueError, match="K = 5"):
        rotate_sh(torch.zeros(3, 5, 3), torch.eye(3).expand(3, 3, 3))


def test_gradients_in_coefficients_and_rotation():
    sh = torch.randn(3, 16, 3, dtype=D64, requires_grad=True)
    aa = torch.randn(3, 3, dtype=D64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda s, a: rotate_sh(s, axis_angle_to_rotmat(a)), (sh, aa), eps=1e-6, atol=1e-6)


@pytest.mark.parametrize("degree", [1, 3])
def test_colour_in_frames_and_its_dc_encoding_match_the_rotated_coefficients(degree):
    """The renderer's deferred path: eval in per-Gaussian frames, then as a DC coefficient rendered at degree 0."""
    from framework.splat.sh import eval_sh_in_frames, view_colour_dc

    g = torch.Generator().manual_seed(7 + degree)
    sh = torch.randn(256, 16, 3, generator=g, dtype=D64)
    R = random_rotations(256, 20 + degree)
    d = torch.randn(256, 3, generator=g, dtype=D64) * 4.0  # raw, unnormalised mean - camera vectors
    want = eval_sh(degree, rotate_sh(sh[:, : (degree + 1) ** 2], R), d)
    assert (eval_sh_in_frames(degree, sh, d, R) - want).abs().max() < 1e-10
    dc = view_colour_dc(degree, sh, d, R)  # [N, 1, 3]
    assert dc.shape == (256, 1, 3)
    assert (eval_sh(0, dc, d) - want).abs().max() < 1e-10

"""quat_to_rotmat's closed-form backward against an independent formula and finite differences."""

from __future__ import annotations

import torch

from framework.geometry import quat_to_rotmat


def _rotmat_rodrigues(q: torch.Tensor) -> torch.Tensor:
    """R = I + 2 w [v]x + 2 [v]x^2 for the unit quaternion (w, v): a different construction from the library's."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, v = q[..., :1], q[..., 1:]
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    K = torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*v.shape, 3)  # [v]x
    eye = torch.eye(3, dtype=q.dtype).expand_as(K)
    return eye + 2 * w[..., None] * K + 2 * K @ K


def test_values_and_gradients_match_rodrigues() -> None:
    g = torch.Generator().manual_seed(0)
    q = (torch.randn(200, 4, generator=g, dtype=torch.float64) * torch.rand(200, 1, generator=g) * 3).requires_grad_()
    q2 = q.detach().clone().requires_grad_()
    w = torch.randn(200, 3, 3, generator=g, dtype=torch.float64)
    R, R_ref = quat_to_rotmat(q), _rotmat_rodrigues(q2)
    assert torch.allclose(R, R_ref, atol=1e-12)
    (g1,) = torch.autograd.grad((R * w).sum(), q)
    (g2,) = torch.autograd.grad((R_ref * w).sum(), q2)
    assert torch.allclose(g1, g2, atol=1e-11, rtol=1e-10)


def test_gradcheck_and_batch_dims() -> None:
    q = torch.randn(2, 5, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1)).requires_grad_()
    assert torch.autograd.gradcheck(quat_to_rotmat, (q,))


def test_zero_quaternion_is_identity_with_zero_gradient() -> None:
    q = torch.zeros(3, 4, dtype=torch.float64, requires_grad=True)
    R = quat_to_rotmat(q)
    assert torch.equal(R, torch.eye(3, dtype=torch.float64).expand(3, 3, 3))
    (grad,) = torch.autograd.grad(R.sum(), q)
    assert torch.equal(grad, torch.zeros_like(grad))

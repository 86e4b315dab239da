"""quat_to_rotmat's closed-form backward and rotmat_to_quat against an independent formula and finite differences.

Every test runs twice: on the CPU's forms (entry by entry, a closed-form backward) and on the few-kernel forms an
accelerator takes (`framework.geometry.few_kernels`; here under the torch execution)."""

from __future__ import annotations

import functools
import math

import pytest
import torch

from framework.execution import COMPILED, TORCH, Execution
from framework.geometry import (
    axis_angle_to_rotmat,
    few_kernels,
    quat_multiply,
    quat_normalize,
    quat_to_rotmat,
    quat_to_rotmat_entry_major,
    rotmat_to_quat,
)


@pytest.fixture(autouse=True, params=["cpu_forms", "few_kernels"])
def forms(request: pytest.FixtureRequest) -> str:
    return request.param


@pytest.fixture
def execution(forms: str) -> Execution:
    """The compiled execution takes the CPU's forms, the torch execution (a GPU's code) the few-kernel forms."""
    execution = COMPILED if forms == "cpu_forms" else TORCH
    assert few_kernels(torch.zeros(1), execution) is (forms == "few_kernels")
    return execution


def _rotmat_rodrigues(q: torch.Tensor) -> torch.Tensor:
    """R = I + 2 w [v]x + 2 [v]x^2 for the unit quaternion (w, v): a different construction from the library's."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, v = q[..., :1], q[..., 1:]
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    K = torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*v.shape, 3)  # [v]x
    eye = torch.eye(3, dtype=q.dtype).expand_as(K)
    return eye + 2 * w[..., None] * K + 2 * K @ K


def test_values_and_gradients_match_rodrigues(execution) -> None:
    g = torch.Generator().manual_seed(0)
    q = (torch.randn(200, 4, generator=g, dtype=torch.float64) * torch.rand(200, 1, generator=g) * 3).requires_grad_()
    q2 = q.detach().clone().requires_grad_()
    w = torch.randn(200, 3, 3, generator=g, dtype=torch.float64)
    R, R_ref = quat_to_rotmat(q, execution=execution), _rotmat_rodrigues(q2)
    assert torch.allclose(R, R_ref, atol=1e-12)
    (g1,) = torch.autograd.grad((R * w).sum(), q)
    (g2,) = torch.autograd.grad((R_ref * w).sum(), q2)
    assert torch.allclose(g1, g2, atol=1e-11, rtol=1e-10)


def test_entry_major_form_matches_rodrigues_with_zero_rows(execution) -> None:
    """[4, N] -> [9, N]: values and gradients against the Rodrigues construction (row-major, float64), with two zero
    quaternions among them (the identity, with a zero gradient)."""
    g = torch.Generator().manual_seed(2)
    q = torch.randn(50, 4, generator=g, dtype=torch.float64) * 2
    q[[3, 17]] = 0.0
    q = q.requires_grad_()
    q2 = q.detach().clone().requires_grad_()
    w = torch.randn(50, 3, 3, generator=g, dtype=torch.float64)
    R = quat_to_rotmat_entry_major(q.t(), execution=execution)  # [9, N]
    R_ref = torch.where(q2.detach().abs().sum(-1)[:, None, None] > 0, _rotmat_rodrigues(q2), torch.eye(3).double())
    torch.testing.assert_close(R, R_ref.reshape(50, 9).t(), atol=1e-12, rtol=0)
    (g1,) = torch.autograd.grad((R * w.reshape(50, 9).t()).sum(), q)
    (g2,) = torch.autograd.grad((R_ref * w).sum(), q2)
    torch.testing.assert_close(g1, torch.nan_to_num(g2), atol=1e-11, rtol=1e-10)
    assert torch.equal(g1[[3, 17]], torch.zeros(2, 4, dtype=torch.float64))
    some = q.detach()[:6].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda x: quat_to_rotmat_entry_major(x.t(), execution=execution), (some,))


def test_gradcheck_and_batch_dims(execution) -> None:
    q = torch.randn(2, 5, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1)).requires_grad_()
    assert torch.autograd.gradcheck(functools.partial(quat_to_rotmat, execution=execution), (q,))


def test_zero_quaternion_is_identity_with_zero_gradient(execution) -> None:
    q = torch.zeros(3, 4, dtype=torch.float64, requires_grad=True)
    R = quat_to_rotmat(q, execution=execution)
    assert torch.equal(R, torch.eye(3, dtype=torch.float64).expand(3, 3, 3))
    (grad,) = torch.autograd.grad(R.sum(), q)
    assert torch.equal(grad, torch.zeros_like(grad))


def test_rotmat_to_quat_inverts_rodrigues() -> None:
    """Unit quaternions (w > 0) -> R by Rodrigues (independent of the library) -> back: the same quaternion; every
    quadrant of the four formulas is reached (each of w, x, y, z is the largest component for some rows)."""
    g = torch.Generator().manual_seed(2)
    q = torch.randn(4000, 4, generator=g, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[:, :1] < 0, -q, q)
    assert set(q.abs().argmax(-1).tolist()) == {0, 1, 2, 3}
    assert torch.allclose(rotmat_to_quat(_rotmat_rodrigues(q)), q, atol=1e-13)
    assert rotmat_to_quat(_rotmat_rodrigues(q[:6]).reshape(2, 3, 3, 3)).shape == (2, 3, 4)


def test_rotmat_to_quat_half_turns_and_gradients(execution) -> None:
    """180-degree rotations (w = 0, where the trace formula divides by zero): a quaternion of the same rotation,
    finite gradients; gradcheck (finite differences) on generic rotations (at a half turn the sign convention w >= 0
    flips the quaternion, so finite differences straddle a jump)."""
    axes = torch.tensor([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, -2, 3]], dtype=torch.float64)
    R = axis_angle_to_rotmat(math.pi * axes / axes.norm(dim=-1, keepdim=True), execution=execution).requires_grad_()
    q = rotmat_to_quat(R)
    assert torch.allclose(q[:, 0], torch.zeros(5, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(_rotmat_rodrigues(q), R, atol=1e-12)
    (grad,) = torch.autograd.grad((q * torch.randn(5, 4, dtype=torch.float64)).sum(), R)
    assert torch.isfinite(grad).all()
    generic = axis_angle_to_rotmat(
        torch.randn(6, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3)), execution=execution
    )
    assert torch.autograd.gradcheck(rotmat_to_quat, (generic.requires_grad_(),))


def test_quat_multiply_composes_rotations_in_both_layouts(execution) -> None:
    """R(a * b) = R(a) R(b) with R by Rodrigues (independent of the product's formula), [N, 4] and [4, N]; gradients
    against finite differences."""
    g = torch.Generator().manual_seed(5)
    a, b = (torch.randn(40, 4, generator=g, dtype=torch.float64) for _ in range(2))
    ab = quat_multiply(a, b, execution=execution)
    torch.testing.assert_close(_rotmat_rodrigues(ab), _rotmat_rodrigues(a) @ _rotmat_rodrigues(b), atol=1e-12, rtol=0)
    torch.testing.assert_close(ab.norm(dim=-1), a.norm(dim=-1) * b.norm(dim=-1), atol=1e-12, rtol=0)
    torch.testing.assert_close(quat_multiply(a.t(), b.t(), dim=0, execution=execution), ab.t(), atol=1e-15, rtol=0)
    some = (a[:5].clone().requires_grad_(), b[:5].clone().requires_grad_())
    assert torch.autograd.gradcheck(functools.partial(quat_multiply, execution=execution), some)
    assert torch.autograd.gradcheck(lambda x, y: quat_multiply(x.t(), y.t(), dim=0, execution=execution), some)


@pytest.mark.parametrize("dim", [-1, 0])
def test_quat_normalize_values_and_gradients_against_the_plain_formula(dim, execution) -> None:
    """q / |q| differentiated by autograd in float64 is the reference (the few-kernel form has its own backward);
    gradcheck on top, and a zero quaternion gives the identity with a zero gradient."""
    g = torch.Generator().manual_seed(4)
    q = torch.randn(50, 4, dtype=torch.float64, generator=g)
    q[3] = 0.0
    q = q if dim == -1 else q.t().contiguous()
    up = torch.randn(q.shape, dtype=torch.float64, generator=g)
    x = q.clone().requires_grad_()
    (grad,) = torch.autograd.grad((quat_normalize(x, dim=dim, execution=execution) * up).sum(), x)
    ref_x = q.clone().requires_grad_()
    norm = ref_x.norm(dim=dim, keepdim=True)
    keep = (norm > 1e-12).to(q.dtype)  # the zero row: identity, no gradient
    identity = torch.zeros_like(q)
    identity.select(dim, 0).fill_(1.0)
    ref = keep * ref_x / norm.clamp_min(1e-300) + (1 - keep) * identity
    (ref_grad,) = torch.autograd.grad((ref * up).sum(), ref_x)
    assert torch.allclose(quat_normalize(q, dim=dim, execution=execution), ref, atol=1e-15)
    assert torch.allclose(grad, ref_grad, atol=1e-13)
    zero_row = grad[3] if dim == -1 else grad[:, 3]
    assert (zero_row == 0).all() and (grad.abs().sum(dim) > 0).sum() == 49
    small = (q[4:10] if dim == -1 else q[:, 4:10]).clone().requires_grad_()  # away from the zero one
    assert torch.autograd.gradcheck(lambda t: quat_normalize(t, dim=dim, execution=execution), (small,))


def test_axis_angle_gradients_against_the_plain_formula_and_at_zero(execution) -> None:
    """Away from zero: autograd through I + sin(t)/t K + (1 - cos t)/t^2 K^2 written out here (float64) is the
    reference (the few-kernel form has a closed-form backward); at zero the derivative is [e_i]x exactly, so the
    gradient is vee(G) = (G21 - G12, G02 - G20, G10 - G01); gradcheck across the Taylor threshold."""
    g = torch.Generator().manual_seed(5)
    aa = torch.randn(4, 7, 3, dtype=torch.float64, generator=g) * 1.3
    aa[0, 0] = torch.tensor([math.pi, 0.0, 0.0])
    G = torch.randn(4, 7, 3, 3, dtype=torch.float64, generator=g)
    x = aa.clone().requires_grad_()
    (grad,) = torch.autograd.grad(axis_angle_to_rotmat(x, execution=execution), x, G)
    r = aa.clone().requires_grad_()
    t = r.norm(dim=-1)[..., None, None]
    zero = torch.zeros_like(r[..., 0])
    K = torch.stack([zero, -r[..., 2], r[..., 1], r[..., 2], zero, -r[..., 0], -r[..., 1], r[..., 0], zero], -1)
    K = K.unflatten(-1, (3, 3))
    ref = torch.eye(3, dtype=torch.float64) + torch.sin(t) / t * K + (1 - torch.cos(t)) / t**2 * (K @ K)
    (ref_grad,) = torch.autograd.grad(ref, r, G)
    assert torch.allclose(axis_angle_to_rotmat(aa, execution=execution), ref.detach(), atol=1e-14)
    assert torch.allclose(grad, ref_grad, atol=1e-12)
    z = torch.zeros(5, 3, dtype=torch.float64, requires_grad=True)
    Gz = torch.randn(5, 3, 3, dtype=torch.float64, generator=g)
    (gz,) = torch.autograd.grad(axis_angle_to_rotmat(z, execution=execution), z, Gz)
    vee = torch.stack([Gz[:, 2, 1] - Gz[:, 1, 2], Gz[:, 0, 2] - Gz[:, 2, 0], Gz[:, 1, 0] - Gz[:, 0, 1]], -1)
    assert torch.allclose(gz, vee, atol=1e-15)
    near = torch.tensor([[5e-5, 0.0, 0.0], [0.0, 2e-4, -1e-4], [0.3, -0.2, 0.1]], dtype=torch.float64)
    assert torch.autograd.gradcheck(
        functools.partial(axis_angle_to_rotmat, execution=execution), (near.requires_grad_(),)
    )

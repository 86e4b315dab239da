"""Polar decomposition: values against float64 SVD, gradients against finite differences, extremes stay finite."""

from __future__ import annotations

import functools
import math

import pytest
import torch

from framework.execution import COMPILED, TORCH, Execution
from framework.geometry import axis_angle_to_rotmat
from framework.rig.polar import polar_decompose, polar_rotation, polar_rotation_values

torch.manual_seed(0)
D64 = torch.float64
EYE = torch.eye(3, dtype=D64)


@pytest.fixture(autouse=True, params=["cpu", "accelerator"])
def code_path(request) -> str:
    """Every test runs both forms of the Newton routing: the CPU's (checked after each step) and an accelerator's
    (fixed steps, then one host read), which the torch execution makes a CPU run."""
    return request.param


@pytest.fixture
def execution(code_path: str) -> Execution:
    return COMPILED if code_path == "cpu" else TORCH


def svd_rotation(A: torch.Tensor) -> torch.Tensor:
    U, _, Vh = torch.linalg.svd(A.double())
    d = torch.linalg.det(U @ Vh)
    U = torch.cat([U[..., :2], U[..., 2:] * d.sign()[..., None, None]], dim=-1)
    return U @ Vh


def lbs_blends(n: int, joints: int = 4, max_angle: float = 2.0, dtype=D64) -> torch.Tensor:
    g = torch.Generator().manual_seed(1)
    w = torch.rand(n, joints, generator=g, dtype=dtype)
    w = w / w.sum(1, keepdim=True)
    Rk = axis_angle_to_rotmat(torch.randn(joints, 3, generator=g, dtype=dtype).clamp(-1, 1) * max_angle)
    return torch.einsum("nj,jab->nab", w, Rk)


@pytest.mark.parametrize("kind", ["random", "lbs"])
def test_values_match_svd(kind, execution):
    A = torch.randn(500, 3, 3, dtype=D64) if kind == "random" else lbs_blends(500)
    R, S = polar_decompose(A, execution=execution)
    ref = svd_rotation(A)
    assert torch.allclose(R, ref, atol=1e-10)
    assert torch.allclose(R.mT @ R, EYE.expand_as(R), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(500, dtype=D64), atol=1e-12)
    assert torch.allclose(S, S.mT, atol=1e-12)
    pos = torch.linalg.det(A) > 0
    assert torch.linalg.eigvalsh(S[pos]).min() > -1e-10  # PSD where det > 0
    assert torch.allclose(R @ S, A, atol=1e-10)


@pytest.mark.parametrize("kind", ["random", "lbs"])
def test_newton_forward_matches_svd_forward(kind, execution):
    A = torch.randn(300, 3, 3, dtype=D64) if kind == "random" else lbs_blends(300)
    A[:3] = _extremes(D64)[[2, 4, 9]]  # rank 1, zero, reflection: routed to the SVD inside the Newton path
    assert torch.allclose(
        polar_rotation_values(A, "newton", execution=execution),
        polar_rotation_values(A, "svd", execution=execution),
        atol=1e-10,
    )


def test_float32_newton_is_within_float32_rounding_of_float64_svd(execution):
    """Training default: float32 inputs iterate in float32; the float64 SVD of the same matrices is the reference."""
    A = lbs_blends(2000, joints=6, max_angle=2.5).float()
    ref = svd_rotation(A.double())
    r32 = polar_rotation_values(A, execution=execution)
    assert r32.dtype == torch.float32
    assert (r32.double() - ref).abs().max() < 1e-6
    r64 = polar_rotation_values(A, dtype=torch.float64, execution=execution)  # float64 iteration, float32 result
    assert (r64.double() - ref).abs().max() < 1e-7
    with pytest.raises(ValueError, match="dtype"):
        polar_rotation_values(A, dtype=torch.float16, execution=execution)


def test_reflection_gives_closest_proper_rotation(execution):
    A = torch.randn(200, 3, 3, dtype=D64)
    A[:, :, 0] *= torch.where(torch.linalg.det(A) > 0, -1.0, 1.0).to(D64)[:, None]  # make every det negative
    assert (torch.linalg.det(A) < 0).all()
    R = polar_rotation(A, execution=execution)
    assert torch.allclose(torch.linalg.det(R), torch.ones(200, dtype=D64), atol=1e-10)
    assert torch.allclose(R, svd_rotation(A), atol=1e-8)


def test_gradcheck_generic(execution):
    A = (torch.randn(6, 3, 3, dtype=D64) + 2.5 * EYE).requires_grad_()
    assert torch.autograd.gradcheck(functools.partial(polar_rotation, execution=execution), (A,), eps=1e-6, atol=1e-6)


@pytest.mark.parametrize("scale", [1.0, 0.3, 7.0])
def test_gradcheck_at_equal_singular_values(scale, execution):
    """A = c R (rigid blends): SVD gradients are undefined here, the polar rotation's are not."""
    R0 = axis_angle_to_rotmat(torch.tensor([[0.3, -1.2, 0.5], [0.0, 0.0, 0.0]], dtype=D64))
    A = (scale * R0).requires_grad_()
    assert torch.autograd.gradcheck(
        functools.partial(polar_rotation, execution=execution), (A,), eps=1e-6, atol=1e-5, rtol=1e-3
    )


def test_gradcheck_lbs_blends(execution):
    A = lbs_blends(5, max_angle=1.0).requires_grad_()
    assert torch.autograd.gradcheck(lambda a: polar_decompose(a, execution=execution)[1], (A,), eps=1e-6, atol=1e-6)


def _extremes(dtype) -> torch.Tensor:
    big = 1e4 if dtype == torch.float16 else 1e6  # float16 overflows at 65504
    R = axis_angle_to_rotmat(torch.tensor([0.2, 0.4, -0.3], dtype=D64))
    flip = axis_angle_to_rotmat(torch.tensor([0.0, math.pi, 0.0], dtype=D64))
    cases = [
        EYE,
        R,
        0.5 * R + 0.5 * R @ flip,  # antipodal bones in one blend: rank 1
        0.5 * EYE + 0.5 * axis_angle_to_rotmat(torch.tensor([math.pi - 1e-4, 0.0, 0.0], dtype=D64)),  # near it
        torch.zeros(3, 3, dtype=D64),
        1e-6 * R,
        big * R,
        torch.diag(torch.tensor([1.0, 1.0, 1e-9], dtype=D64)),  # near singular
        torch.diag(torch.tensor([2.0, 2.0, 2.0], dtype=D64)),
        -EYE,  # det < 0
    ]
    return torch.stack(cases).to(dtype)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.float16, torch.bfloat16])
def test_extremes_finite_values_and_gradients(dtype, execution):
    A = _extremes(dtype).requires_grad_()
    R, S = polar_decompose(A, execution=execution)
    assert R.dtype == dtype
    assert torch.isfinite(R).all() and torch.isfinite(S).all()
    R64 = R.double()
    tol = 1e-5 if dtype in (torch.float64, torch.float32) else 2e-2
    assert torch.allclose(R64.mT @ R64, EYE.expand_as(R64), atol=tol)
    (R.double() * torch.randn(R.shape, dtype=D64)).sum().backward()
    assert torch.isfinite(A.grad).all()
    assert A.grad.double().abs().max() < 1e7


def test_rank_deficient_rotation_still_maps_the_determined_direction(execution):
    """For the 50/50 antipodal blend A = R (2 a a^T)/2 only R a is determined; check it."""
    R = axis_angle_to_rotmat(torch.tensor([0.2, 0.4, -0.3], dtype=D64))
    flip = axis_angle_to_rotmat(torch.tensor([0.0, math.pi, 0.0], dtype=D64))
    out = polar_rotation((0.5 * R + 0.5 * R @ flip)[None], execution=execution)[0]
    a = torch.tensor([0.0, 1.0, 0.0], dtype=D64)
    assert torch.allclose(out @ a, R @ a, atol=1e-10)


def test_empty_and_batched_shapes(execution):
    assert polar_rotation(torch.zeros(0, 3, 3), execution=execution).shape == (0, 3, 3)
    A = torch.randn(2, 5, 3, 3, dtype=D64) + 3 * EYE
    assert torch.allclose(polar_rotation(A, execution=execution), svd_rotation(A), atol=1e-10)
    with pytest.raises(ValueError, match=r"\[\.\.\., 3, 3\]"):
        polar_rotation(torch.zeros(4, 2, 2), execution=execution)


def test_non_finite_matrices_give_the_identity_and_leave_the_others_alone(execution):
    """A NaN or inf entry (a diverged blend) gives the identity rotation for that matrix only."""
    A = lbs_blends(50, max_angle=1.0).float()
    A[7, 1, 2] = float("nan")
    A[20, 0, 0] = float("inf")
    R = polar_rotation_values(A, execution=execution)
    bad = torch.zeros(50, dtype=torch.bool)
    bad[[7, 20]] = True
    assert torch.isfinite(R).all()
    assert torch.equal(R[bad], torch.eye(3).expand(2, 3, 3))
    assert (R[~bad].double() - svd_rotation(A[~bad].double())).abs().max() < 1e-6


def _count_host_reads(fn) -> int:
    """Host reads of tensor values (`item`, `float`, `bool`) while fn runs."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class Reads(TorchDispatchMode):
        n = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func is torch.ops.aten._local_scalar_dense.default:
                Reads.n += 1
            return func(*args, **(kwargs or {}))

    with Reads():
        fn()
    return Reads.n


@pytest.mark.parametrize("ratio, reads_on_accelerator", [(0.7, 1), (0.1, 1), (0.01, None)])
def test_accelerator_form_reads_the_host_once_for_well_conditioned_blends(
    code_path, ratio, reads_on_accelerator, execution
):
    """Rotations times diag(1, (1 + r) / 2, r): the accelerator's form converges in its fixed steps down to r = 0.1
    and reads one value; at r = 0.01 it falls back to the checked iteration, which still matches the SVD."""
    g = torch.Generator().manual_seed(3)
    R = axis_angle_to_rotmat(torch.randn(200, 3, generator=g, dtype=D64))
    A = (R @ torch.diag(torch.tensor([1.0, (1 + ratio) / 2, ratio], dtype=D64))).float()
    out = []
    reads = _count_host_reads(lambda: out.append(polar_rotation_values(A, execution=execution)))
    assert (out[0].double() - svd_rotation(A.double())).abs().max() < 2e-6
    if code_path == "accelerator" and reads_on_accelerator is not None:
        assert reads == reads_on_accelerator
    else:
        assert reads >= 2  # the routing test and at least one convergence check


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_polar_reads_the_host_once_and_matches_svd(code_path, execution):
    """On CUDA the accelerator's form runs whatever the execution says (CUDA tensors are never compiled)."""
    A = lbs_blends(5000, joints=4, max_angle=1.0).float()
    out = []
    reads = _count_host_reads(lambda: out.append(polar_rotation_values(A.cuda(), execution=execution)))
    assert reads == 1
    assert (out[0].double().cpu() - svd_rotation(A.double())).abs().max() < 2e-6

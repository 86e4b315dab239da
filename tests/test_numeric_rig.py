"""Numerical extremes of the deformers' math (hypothesis): polar decomposition, linear blend skinning, SH rotation.

Every property compares with an independent float64 reference (SVD, a per-joint blend loop, the SH identity
f'(d) = f(R^T d)) where the answer is unique, and otherwise checks that the documented guard of
`framework.guards` is exactly what happens. Tolerances (float32): polar rotation 50 eps * s_1 / gap (the rotation's
condition number), LBS means 1e-5 relative to the transformed extent, SH rotation 2e-6 relative to the coefficients;
half precision one unit in the last place of the output dtype.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from hypothesis import given
from hypothesis import strategies as st

from framework.geometry import quat_normalize, quat_to_rotmat
from framework.guards import LBS_MIN_STRETCH, POLAR_DAMPING_FLOOR, POLAR_TIKHONOV
from framework.rig.kinematics import forward_kinematics
from framework.rig.lbs import apply_lbs
from framework.rig.polar import polar_decompose
from framework.rig.sh_rotation import rotate_sh
from framework.splat.sh import eval_sh
from framework.types import Gaussians

D64 = torch.float64
EPS = {torch.float32: 2.0**-23, torch.float64: 2.0**-52}
finite = {"allow_nan": False, "allow_infinity": False}


def rotation(axis: np.ndarray, angle: float) -> torch.Tensor:
    a = torch.tensor(axis, dtype=D64)
    return torch.linalg.matrix_exp(torch.cross(torch.eye(3, dtype=D64), (a / a.norm() * angle).expand(3, 3), dim=-1))


axes = st.tuples(*[st.floats(-1, 1, **finite)] * 3).filter(lambda v: np.linalg.norm(v) > 0.1).map(np.array)


# --------------------------------------------------------------------------------------------------------- polar
@st.composite
def matrices(draw: st.DrawFn) -> tuple[str, torch.Tensor]:
    """3x3 matrices of every kind LBS can produce and some it cannot: R1 diag(s) R2^T with s spanning 1e-6..1e6
    (condition numbers up to 1e12), rank 2, rank 1, zero, reflections (det < 0), and 50/50 or near-50/50 blends of
    antipodal bone rotations (rank 1 exactly at 50/50)."""
    kind = draw(st.sampled_from(["general", "rank2", "rank1", "zero", "reflected", "antipodal", "near_antipodal"]))
    R1 = rotation(draw(axes), draw(st.floats(0, math.pi)))
    R2 = rotation(draw(axes), draw(st.floats(0, math.pi)))
    mag = 10 ** draw(st.floats(-6, 6))
    s = torch.tensor([10 ** draw(st.floats(-6, 0)) for _ in range(3)], dtype=D64).sort(descending=True).values * mag
    if kind == "rank2":
        s[2] = 0.0
    elif kind == "rank1":
        s[1:] = 0.0
    elif kind == "zero":
        s[:] = 0.0
    elif kind == "reflected":
        s[2] = -s[2]
    if kind in ("antipodal", "near_antipodal"):
        w = 0.5 if kind == "antipodal" else 0.5 + draw(st.sampled_from([1e-6, 1e-3, -1e-2]))
        A = w * R1 + (1 - w) * R1 @ rotation(draw(axes), math.pi)
    else:
        A = R1 @ torch.diag(s) @ R2.T
    return kind, A


def svd_polar(A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """float64 reference: R (closest proper rotation), the signed singular values sigma of S, and S's eigenbasis V."""
    U, s, Vh = torch.linalg.svd(A.double())
    d = torch.ones(3, dtype=D64)
    d[2] = torch.sign(torch.linalg.det(U @ Vh))
    return U @ torch.diag(d) @ Vh, s * d, Vh.T, d


def damped_polar_gradient(A: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """dL/dA of L = <G, R(A)> with the Tikhonov damping of `framework.guards.POLAR_TIKHONOV`, from the SVD.

    In the eigenbasis V of S (eigenvalues sigma), the exact gradient divides the skew part of R^T G by
    sigma_j + sigma_k; damped, it multiplies by (sigma_j + sigma_k) / ((sigma_j + sigma_k)^2 + d^2), d = 1e-3 |tr S|.
    """
    R, sigma, V, _ = svd_polar(A)
    G = G.double()
    K = R.T @ G - G.T @ R
    g = torch.stack([K[2, 1], K[0, 2], K[1, 0]])  # vee
    pair = sigma.sum() - sigma  # [3]: sigma_j + sigma_k for axis i
    d2 = (POLAR_TIKHONOV * sigma.sum().abs()) ** 2 + POLAR_DAMPING_FLOOR
    h = V @ ((pair / (pair**2 + d2)) * (V.T @ g))
    x, y, z = h
    skew = torch.stack([torch.stack([0 * x, -z, y]), torch.stack([z, 0 * x, -x]), torch.stack([-y, x, 0 * x])])
    return R @ skew


@given(case=matrices(), dtype=st.sampled_from([torch.float32, torch.float64]), seed=st.integers(0, 1000))
def test_polar_extremes(case, dtype, seed) -> None:
    """R is a finite proper rotation for every input; it is the SVD's wherever the rotation is determined; the
    gradient is finite and equals the damped closed form (POLAR_TIKHONOV), so it stays bounded at rank 1 and 0."""
    kind, A64 = case
    A = A64.to(dtype).requires_grad_()
    R, S = polar_decompose(A)
    G = torch.randn(3, 3, generator=torch.Generator().manual_seed(seed), dtype=D64)
    (grad,) = torch.autograd.grad((R * G.to(dtype)).sum(), A)
    R, S = R.detach(), S.detach()
    assert torch.isfinite(R).all() and torch.isfinite(S).all() and torch.isfinite(grad).all(), kind
    eye = torch.eye(3, dtype=D64)
    tol = 100 * EPS[dtype]
    assert (R.double().T @ R.double() - eye).abs().max() <= tol and abs(float(torch.linalg.det(R.double())) - 1) <= tol
    Ain = A.detach().double()  # the reference sees exactly the input (already rounded to dtype)
    R_ref, sigma, _, _ = svd_polar(Ain)
    s = sigma.abs()
    gap = float((sigma.sum() - sigma).min())  # smallest sigma_j + sigma_k: where the rotation is determined
    if gap > 1e-3 * float(s.max()):
        assert (R.double() - R_ref).abs().max() <= 50 * EPS[dtype] * float(s.max()) / gap + tol, kind
        torch.testing.assert_close(R.double() @ S.double(), Ain, atol=50 * EPS[dtype] * float(s.max()), rtol=0)
    # gradient: the damped closed form, computed from the SVD rather than the backward's 3x3 solve
    ref = damped_polar_gradient(Ain, G.to(dtype).double())
    d = math.sqrt((POLAR_TIKHONOV * float(sigma.sum().abs())) ** 2 + POLAR_DAMPING_FLOOR)
    bound = float(G.norm()) / d  # |R skew(h)| = sqrt 2 |h| <= sqrt 2 |g| / (2 d), |g| <= sqrt 2 |G|
    assert float(grad.double().norm()) <= 1.01 * bound + 1e-6, kind
    if gap > 1e-3 * float(s.max()) or kind in ("rank1", "zero", "antipodal"):
        scale = float(ref.norm()) + float(G.norm()) * 1e-6
        assert float((grad.double() - ref).norm()) <= 1e-3 * scale + 1e3 * EPS[dtype] * bound, kind


def test_polar_gradient_of_rank_one_blend_is_the_damped_one() -> None:
    """A 50/50 blend of a bone and its 180-degree turn (rank 1): the rotation about the kept axis is undetermined, the
    exact gradient infinite; the guard's damping gives |grad| = |g| / (2 d) along the free axes, d = 1e-3 tr(S)."""
    A = (0.5 * (torch.eye(3, dtype=D64) + rotation(np.array([0.0, 0.0, 1.0]), math.pi))).requires_grad_()
    R, _ = polar_decompose(A)
    G = torch.zeros(3, 3, dtype=D64)
    G[0, 1], G[1, 0] = 1.0, -1.0  # pushes the rotation about z: sigma_x + sigma_y = 0 there
    (grad,) = torch.autograd.grad((R * G).sum(), A)
    torch.testing.assert_close(grad, damped_polar_gradient(A.detach(), G), atol=1e-8, rtol=0)
    # the pair sum is 0 up to rounding (~1e-16): the damped factor ~1e-16 / d^2 ~ 1e-10 instead of 1 / 0
    assert float(grad.norm()) <= 1e-8


# ----------------------------------------------------------------------------------------------------------- LBS
@st.composite
def lbs_cases(draw: st.DrawFn):
    """Poses with joint angles inside a human range, far outside it (up to 1000 rad) or exactly pi; weights that are a
    partition of unity, scaled (sum 0.3 or 2), all zero, one-hot, or 50/50 between a bone and a bone turned by pi;
    Gaussians with scales 1e-7..1e3 and quaternions of norm 0..1e3."""
    J, N = 4, 6
    g = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    angle_kind = draw(st.sampled_from(["human", "far", "pi"]))
    directions = torch.nn.functional.normalize(torch.randn(1, J, 3, generator=g, dtype=D64), dim=-1)
    if angle_kind == "human":
        pose = directions * torch.rand(1, J, 1, generator=g, dtype=D64) * 2.5
    elif angle_kind == "far":
        pose = directions * torch.empty(1, J, 1, dtype=D64).uniform_(10.0, 1000.0, generator=g)
    else:
        pose = directions * math.pi
    joints = torch.randn(J, 3, generator=g, dtype=D64) * 0.3
    _, T = forward_kinematics(pose, joints, [-1, 0, 1, 1])  # [1, J, 4, 4]
    T = T[0]
    weight_kind = draw(st.sampled_from(["unity", "scaled", "zero", "one_hot", "antipodal"]))
    w = torch.rand(N, J, generator=g, dtype=D64) ** 3
    w = w / w.sum(1, keepdim=True)
    if weight_kind == "scaled":
        w = w * draw(st.sampled_from([0.3, 2.0]))
    elif weight_kind == "zero":
        w = torch.zeros(N, J, dtype=D64)
    elif weight_kind == "one_hot":
        w = torch.nn.functional.one_hot(torch.randint(0, J, (N,), generator=g), J).to(D64)
    elif weight_kind == "antipodal":
        flip = torch.eye(4, dtype=D64)
        flip[:3, :3] = rotation(draw(axes), math.pi)
        T = T.clone()
        T[1] = T[0] @ flip  # bone 1 = bone 0 turned by pi about an axis through its origin
        w = torch.zeros(N, J, dtype=D64)
        w[:, 0] = w[:, 1] = 0.5
    log_scales = torch.empty(N, 3, dtype=D64).uniform_(math.log(1e-7), math.log(1e3), generator=g)
    quats = torch.randn(N, 4, generator=g, dtype=D64) * draw(st.sampled_from([0.0, 1e-20, 1e-3, 1.0, 1e3]))
    means = torch.randn(N, 3, generator=g, dtype=D64) * 0.5
    sh = torch.randn(N, 4, 3, generator=g, dtype=D64)
    return f"{angle_kind}/{weight_kind}", means, quats, log_scales, sh, w, T


@given(case=lbs_cases(), dtype=st.sampled_from([torch.float32, torch.float64]))
def test_lbs_extremes(case, dtype) -> None:
    """Posed Gaussians are finite with finite gradients for every case; means equal the per-joint float64 blend
    sum_k w_k (R_k x + t_k); where the blend's rotation is determined, quats and scales equal the SVD reference; the
    stretch is floored at exactly LBS_MIN_STRETCH."""
    kind, means, quats, log_scales, sh, w, T = case
    inputs = [t.to(dtype).requires_grad_() for t in (means, quats, log_scales, sh, w, T)]
    g = Gaussians(inputs[0], inputs[1], inputs[2], torch.zeros(means.shape[0], dtype=dtype), inputs[3])
    posed = apply_lbs(g, inputs[4], inputs[5])
    outs = (posed.means, posed.quats, posed.log_scales, posed.sh)
    assert all(torch.isfinite(o).all() for o in outs), kind
    loss = sum((o * torch.linspace(-1, 1, o.numel(), dtype=dtype).reshape(o.shape)).sum() for o in outs)
    grads = torch.autograd.grad(loss, inputs)
    assert all(torch.isfinite(gr).all() for gr in grads), kind

    x, qd, ld, wd, Td = (t.detach().double() for t in (inputs[0], inputs[1], inputs[2], inputs[4], inputs[5]))
    A_ref = torch.zeros(x.shape[0], 3, 3, dtype=D64)
    t_ref = torch.zeros(x.shape[0], 3, dtype=D64)
    for k in range(Td.shape[0]):  # the blend, one joint at a time
        A_ref += wd[:, k, None, None] * Td[k, :3, :3]
        t_ref += wd[:, k, None] * Td[k, :3, 3]
    mean_ref = (A_ref @ x.unsqueeze(-1)).squeeze(-1) + t_ref
    extent = float(mean_ref.abs().max()) + float(Td[:, :3, 3].abs().max()) + 1.0
    assert float((posed.means.detach().double() - mean_ref).abs().max()) <= 1e3 * EPS[dtype] * extent, kind
    for i in range(x.shape[0]):
        R_ref, sigma, _, _ = svd_polar(A_ref[i])
        Q = quat_to_rotmat(qd[i])
        S_ref = R_ref.T @ A_ref[i]
        k_ref = ((0.5 * (S_ref + S_ref.T)) @ Q * Q).sum(0)
        expected_log = ld[i] + torch.log(k_ref.clamp_min(LBS_MIN_STRETCH))
        got_log = posed.log_scales[i].detach().double()
        floored = k_ref < LBS_MIN_STRETCH
        # where the stretch is floored, the guard is exactly what happens (up to the rounding of ld)
        assert torch.allclose(got_log[floored], (ld[i] + math.log(LBS_MIN_STRETCH))[floored], atol=1e-5), kind
        gap = float((sigma.sum() - sigma).min())
        if gap > 1e-2 * float(sigma.abs().max()) and not floored.any():
            tol = 1e4 * EPS[dtype] * float(sigma.abs().max()) / gap
            R_got = quat_to_rotmat(posed.quats[i].detach().double())
            assert (R_got - R_ref @ quat_to_rotmat(quat_normalize(qd[i]))).abs().max() <= tol + 1e-12, kind
            assert (got_log - expected_log).abs().max() <= tol / float(k_ref.min()) + 1e-5, kind


def test_all_zero_weights_collapse_to_the_stretch_floor() -> None:
    """Weights that are all zero (a Gaussian outside every bone's reach): A = 0, t = 0, so the mean goes to the origin,
    the rotation is the identity and every scale is multiplied by exactly LBS_MIN_STRETCH (not 0, not NaN)."""
    g = Gaussians(torch.randn(3, 3), torch.randn(3, 4), torch.randn(3, 3), torch.zeros(3), torch.randn(3, 1, 3))
    posed = apply_lbs(g, torch.zeros(3, 2), torch.eye(4).expand(2, 4, 4))
    assert torch.equal(posed.means, torch.zeros(3, 3))
    torch.testing.assert_close(posed.log_scales, g.log_scales + math.log(LBS_MIN_STRETCH))
    torch.testing.assert_close(quat_to_rotmat(posed.quats), quat_to_rotmat(g.quats), atol=1e-6, rtol=0)


def test_weight_lookup_at_non_finite_and_far_points() -> None:
    """The blend-weight field's corner gather at points far outside its box, at +-inf and at NaN: each takes the
    values and gradients of torch's grid_sample (border padding, float64) at the point it clamps to (zero gradient
    along the clamped axes), a NaN coordinate clamping to the box's low face instead of gathering at an undefined
    index (the NaN still reaches the loss through the Gaussian's mean)."""
    import torch.nn.functional as F

    from framework.rig.weight_field import WeightField

    g = torch.Generator().manual_seed(3)
    vol = torch.rand(4, 3, 4, 5, generator=g) + 0.1  # [J, D, H, W]
    bounds = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 2.0, 1.0]])
    field = WeightField(vol, bounds)
    inf, nan = float("inf"), float("nan")
    x = torch.tensor([[1e30, -1e30, 0.3], [inf, 0.2, -inf], [-3e38, 3e38, 3e38], [nan, 0.5, 0.5]], requires_grad=True)
    w = field.sample(x)
    assert torch.isfinite(w).all() and torch.allclose(w.sum(-1), torch.ones(4))
    proj = torch.arange(1.0, 5.0)
    (w * proj).sum().backward()
    lo, hi = bounds.double()
    edge = torch.maximum(torch.minimum(x.detach().double().nan_to_num(nan=-inf), hi), lo).requires_grad_()
    ref = F.grid_sample(
        vol.double()[None],
        (2 * (edge - lo) / (hi - lo) - 1)[None, None, None],
        mode="bilinear",
        padding_mode="border",
        align_corners=True,
    )[0, :, 0, 0].t()
    ref = ref / ref.sum(-1, keepdim=True)
    (ref * proj.double()).sum().backward()
    torch.testing.assert_close(w.double(), ref.detach(), atol=1e-6, rtol=0)
    torch.testing.assert_close(x.grad.double(), edge.grad, atol=1e-5, rtol=1e-5)
    assert torch.equal(x.grad[:, 0], torch.zeros(4)) and x.grad[0, 2] != 0


# --------------------------------------------------------------------------------------------------- SH rotation
@st.composite
def sh_cases(draw: st.DrawFn):
    kind = draw(st.sampled_from(["random", "pi", "identity", "near_pi"]))
    angle = {"random": draw(st.floats(0, math.pi)), "pi": math.pi, "identity": 0.0, "near_pi": math.pi - 1e-6}[kind]
    R = rotation(draw(axes), angle)
    degree = draw(st.integers(1, 3))
    mag = draw(st.sampled_from([1e-6, 1.0, 1e3]))
    g = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    sh = mag * torch.randn(5, (degree + 1) ** 2, 3, generator=g, dtype=D64)
    return kind, R, sh, degree


@given(case=sh_cases(), dtype=st.sampled_from([torch.float32, torch.float64, torch.float16, torch.bfloat16]))
def test_sh_rotation_extremes(case, dtype) -> None:
    """eval(rotate_sh(c, R), d) = eval(c, R^T d) for rotations up to (and exactly) pi and coefficients from 1e-6 to
    1e3; half inputs are rotated in float32 and returned rounded (one unit in the last place); gradients finite."""
    kind, R, sh, degree = case
    c = sh.to(dtype).requires_grad_()
    Rin = R.to(dtype if dtype in (torch.float32, torch.float64) else torch.float32).requires_grad_()
    out = rotate_sh(c, Rin.expand(c.shape[0], 3, 3))
    assert out.dtype == dtype and torch.isfinite(out).all(), kind
    out.float().sum().backward()
    assert torch.isfinite(c.grad).all() and torch.isfinite(Rin.grad).all(), kind
    dirs = torch.randn(5, 3, generator=torch.Generator().manual_seed(1), dtype=D64)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    cin = c.detach().double()
    expected = eval_sh(degree, cin, dirs @ R)  # f(R^T d): rows of dirs @ R are R^T d
    got = eval_sh(degree, out.detach().double(), dirs)
    scale = float(cin.abs().max()) * (degree + 1) ** 2
    unit = {torch.float16: 2.0**-10, torch.bfloat16: 2.0**-7}.get(dtype, 0.0)  # the output's own rounding
    subnormal = (degree + 1) ** 2 * torch.finfo(dtype).tiny * torch.finfo(dtype).eps  # float16 below 6e-5: absolute
    tol = (2e-6 if dtype != torch.float64 else 1e-13) * scale + unit * scale + subnormal
    assert float((got - expected).detach().abs().max()) <= tol, kind

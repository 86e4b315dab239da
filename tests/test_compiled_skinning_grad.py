"""The compiled skinning with gradients (`framework.kernels.skinning.lbs_with_sh_frames_trainable`, training on
the CPU) against the torch skinning it replaces: values and the gradients of every input in float64, finite
differences, float32 error, and the deformer's switch."""

from __future__ import annotations

import math

import pytest
import torch

from framework.geometry import axis_angle_to_rotmat
from framework.guards import LBS_MIN_STRETCH
from framework.kernels import skinning as compiled_skinning
from framework.kernels import threads as compiled_threads
from framework.kernels.skinning import lbs_with_sh_frames_trainable
from framework.rig.lbs import lbs_with_sh_frames
from framework.types import Gaussians
from tests.test_compiled_skinning import _gaussians, _transforms, _weights

F64 = torch.float64
TOL = 1e-9  # both in float64; the polar iterations stop at different steps (per matrix here, per batch in torch)


def _forward_backward(fn, g: Gaussians, w: torch.Tensor, T: torch.Tensor, upstream: list[torch.Tensor]):
    """Outputs (means, quats, log_scales, R) and the gradients of (weights, transforms, means, quats, log_scales) of
    sum(output * upstream)."""
    leaves = [t.detach().clone().requires_grad_() for t in (w, T, g.means, g.quats, g.log_scales)]
    posed, R = fn(g.replace(means=leaves[2], quats=leaves[3], log_scales=leaves[4]), leaves[0], leaves[1])
    outputs = [posed.means, posed.quats, posed.log_scales, R]
    sum(((o * u).sum() for o, u in zip(outputs, upstream, strict=True)), torch.zeros((), dtype=w.dtype)).backward()
    return [o.detach() for o in outputs], [t.grad for t in leaves]


def _upstream(n: int, seed: int, dtype: torch.dtype = F64) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(*s, generator=g, dtype=F64).to(dtype) for s in ((n, 3), (n, 4), (n, 3), (n, 3, 3))]


def _hard_cases(n: int) -> tuple[Gaussians, torch.Tensor, torch.Tensor]:
    """Random Gaussians, plus: a zero quaternion (the identity), rotations of 180 degrees about x, y and z (the
    other three rows of rotmat_to_quat), and a bone squashed along z (a stretch k below LBS_MIN_STRETCH, where
    log k is clamped)."""
    g, w, T = _gaussians(n, 5), _weights(n, 24, 6), _transforms(24, 7)
    g.quats[0] = 0.0
    for j, axis in zip((20, 21, 22), torch.eye(3, dtype=F64), strict=True):
        T[j, :3, :3] = axis_angle_to_rotmat(axis * math.pi)
    T[23, :3, :3] = torch.diag(torch.tensor([1.0, 1.0, 1e-5], dtype=F64))
    w[1:5] = 0.0
    w[1, 20], w[2, 21], w[3, 22], w[4, 23] = 1.0, 1.0, 1.0, 1.0
    g.quats[4] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=F64)  # axes = the bone's: k_z = 1e-5
    return g, w, T


@pytest.mark.parametrize("stretch", ["diag", "none"])
@pytest.mark.parametrize("centres", ["blended", "rigid"])
def test_values_and_gradients_match_torch_in_float64(stretch: str, centres: str, monkeypatch) -> None:
    monkeypatch.setattr(compiled_threads, "MIN_CHUNK", 64)  # several chunks on worker threads
    g, w, T = _hard_cases(400)
    up = _upstream(400, 8)
    ref_out, ref_grad = _forward_backward(lambda *a: lbs_with_sh_frames(*a, stretch, F64, centres), g, w, T, up)
    out, grad = _forward_backward(lambda *a: lbs_with_sh_frames_trainable(*a, stretch, centres), g, w, T, up)
    for name, a, b in zip(("means", "quats", "log_scales", "R"), out, ref_out, strict=True):
        torch.testing.assert_close(a, b, atol=TOL, rtol=0, msg=name)
    for name, a, b in zip(("weights", "transforms", "means", "quats", "log_scales"), grad, ref_grad, strict=True):
        torch.testing.assert_close(a, b, atol=TOL, rtol=TOL, msg=f"d/d {name}")
    if stretch == "diag":  # the clamped stretch was reached, and passes no gradient
        posed, _ = lbs_with_sh_frames_trainable(g, w, T, stretch, centres)
        assert float((posed.log_scales[4] - g.log_scales[4]).min()) == pytest.approx(math.log(LBS_MIN_STRETCH))


def test_gradients_match_finite_differences() -> None:
    g, w, T = _gaussians(6, 9), _weights(6, 4, 10), _transforms(4, 11)
    upstream = _upstream(6, 12)

    def loss(w, T, means, quats, log_scales):
        posed, R = lbs_with_sh_frames_trainable(g.replace(means=means, quats=quats, log_scales=log_scales), w, T)
        outputs = (posed.means, posed.quats, posed.log_scales, R)
        return sum((o * u).sum() for o, u in zip(outputs, upstream, strict=True))

    inputs = tuple(t.clone().requires_grad_() for t in (w, T, g.means, g.quats, g.log_scales))
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_float32_error_is_no_worse_than_the_torch_paths() -> None:
    """In float32 both paths differ from the float64 result by rounding; the compiled one (float64 inside) by no
    more than twice what the torch path does (whose polar iteration runs in float32)."""
    g, w, T = _gaussians(2000, 13), _weights(2000, 22, 14), _transforms(22, 15)
    up = _upstream(2000, 16)
    ref_out, ref_grad = _forward_backward(lambda *a: lbs_with_sh_frames(*a, "diag", F64), g, w, T, up)
    g32 = g.replace(**{k: getattr(g, k).float() for k in ("means", "quats", "log_scales")})
    up32 = [u.float() for u in up]
    runs = {
        "torch": _forward_backward(
            lambda *a: lbs_with_sh_frames(*a, "diag", torch.float32), g32, w.float(), T.float(), up32
        ),
        "compiled": _forward_backward(lambda *a: lbs_with_sh_frames_trainable(*a), g32, w.float(), T.float(), up32),
    }
    errors = {
        key: [float((a.double() - b).abs().max()) for a, b in zip(out + grad, ref_out + ref_grad, strict=True)]
        for key, (out, grad) in runs.items()
    }
    for mine, theirs in zip(errors["compiled"], errors["torch"], strict=True):
        assert mine <= 2 * theirs + 1e-6
    assert all(math.isfinite(e) for e in errors["compiled"])


def test_singular_blends_give_finite_gradients() -> None:
    """A 50/50 blend of antipodal rotations (rank 1) and all-zero weights (A = 0): values and gradients finite."""
    g, T = _gaussians(2, 17), _transforms(2, 18, scale=0.0)
    T[1, :3, :3] = T[0, :3, :3] @ axis_angle_to_rotmat(torch.tensor([math.pi, 0.0, 0.0], dtype=F64))
    w = torch.tensor([[0.5, 0.5], [0.0, 0.0]], dtype=F64)
    out, grad = _forward_backward(lbs_with_sh_frames_trainable, g, w, T, _upstream(2, 19))
    assert all(bool(torch.isfinite(t).all()) for t in out + grad)


def test_the_deformer_trains_through_the_compiled_skinning_and_agrees_with_torch(monkeypatch, tmp_path) -> None:
    """`deformer.compiled_skinning` takes the compiled path when gradients are wanted on the CPU (and only then),
    and its outputs and gradients (the Gaussians' and the bone transforms') agree with `compiled_skinning=false` to
    float32 rounding."""
    from framework.model.gaussian_init import from_body_surface
    from framework.plugins import load_plugins
    from framework.registry import REGISTRIES
    from plugins.body.procedural import ProceduralBody

    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(tmp_path))
    load_plugins()
    calls = []
    real = compiled_skinning.lbs_with_sh_frames_trainable
    monkeypatch.setattr(compiled_skinning, "lbs_with_sh_frames_trainable", lambda *a: calls.append(1) or real(*a))
    body = ProceduralBody(segments=8)
    torch.manual_seed(1)
    g0 = from_body_surface(body, 300)
    pose = torch.randn(1, body.num_joints, 3) * 0.4
    bounds = torch.stack([body.rest_vertices.min(0).values - 0.1, body.rest_vertices.max(0).values + 0.1])
    results = {}
    for flag in (True, False):
        deformer = REGISTRIES["deformer"].build("lbs", grid_resolution=12, compiled_skinning=flag)
        deformer.bind(body, bounds)
        g = g0.replace(**{k: getattr(g0, k).clone().requires_grad_() for k in ("means", "quats", "log_scales")})
        T = body.bone_transforms(pose)[0].detach().requires_grad_()
        out = deformer(g, T, defer_sh=True)
        p = out.posed
        loss = p.means.square().sum() + p.quats[:, 1:].sum() + p.log_scales.sum() + (out.sh_frames * 0.3).sum()
        loss = loss + out.aux["weight_std"].sum()
        loss.backward()
        results[flag] = [
            p.means,
            p.quats,
            p.log_scales,
            out.sh_frames,
            g.means.grad,
            g.quats.grad,
            g.log_scales.grad,
            T.grad,
        ]
        if flag:
            assert len(calls) == 1
            with torch.no_grad():  # no gradient wanted: not the trainable loop
                deformer(g0, T.detach(), defer_sh=True)
            assert len(calls) == 1
    assert len(calls) == 1  # compiled_skinning=false: never
    for a, b in zip(results[True], results[False], strict=True):
        a, b = a.detach(), b.detach()
        torch.testing.assert_close(a, b, atol=1e-4 * max(1.0, float(b.abs().max())), rtol=1e-3)

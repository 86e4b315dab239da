"""The compiled blend weights and L_w (`framework.kernels.skin_weights`) against the torch path they replace.

References: the torch path in float64 (`WeightField.sample`, the residual's combination, `weight_std`), which derives
its gradients by autograd through an embedding bag and a softmax, and finite differences (gradcheck)."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from framework.kernels import threads as compiled_threads
from framework.kernels.skin_weights import smooth_weights_compiled
from framework.model.gaussian_init import from_body_surface
from framework.registry import REGISTRIES
from framework.rig.lbs import six_points, weight_std
from framework.rig.weight_field import WeightField

EPS = 1e-6
J = 6


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(tmp_path))


def field_with_rigid_block(dtype=torch.float64) -> WeightField:
    """A random partition-of-unity grid (8 x 9 x 10 nodes) whose corner block is joint 0 alone (L_w = 0 there)."""
    gen = torch.Generator().manual_seed(0)
    vol = torch.rand(J, 8, 9, 10, generator=gen) ** 4
    vol[:, :4, :4, :4] = 0.0
    vol[0, :4, :4, :4] = 1.0
    vol = vol / vol.sum(0, keepdim=True)
    field = WeightField(vol, torch.tensor([[-1.0, -1.2, -0.5], [1.0, 1.0, 0.7]]))
    field.table = field.table.to(dtype)
    return field


def scene(n: int, dtype=torch.float64) -> tuple[Tensor, Tensor]:
    """points [n, 7, 3]: most inside the box, some past its faces, one NaN coordinate, a few Gaussians with all
    seven points in the rigid block; dw [n, 7, J] of both signs, up to about 6."""
    gen = torch.Generator().manual_seed(1)
    lo, hi = torch.tensor([-1.0, -1.2, -0.5], dtype=dtype), torch.tensor([1.0, 1.0, 0.7], dtype=dtype)
    pts = (torch.rand(n, 7, 3, generator=gen, dtype=dtype) * 1.3 - 0.15) * (hi - lo) + lo
    pts[:4] = lo + (hi - lo) * 0.25 * torch.rand(4, 7, 3, generator=gen, dtype=dtype)  # rigid block: cells 0-2
    pts[5, 2, 1] = float("nan")
    dw = torch.randn(n, 7, J, generator=gen, dtype=dtype) * 2.0
    dw[:4] = dw[:4, :1]  # the rigid block's Gaussians: one residual at all seven points, so no spread either
    return pts, dw


def torch_path(field, pts, dw, combine):
    w = field.sample(pts)  # [n, 7, J]
    if combine == "softmax":
        w = torch.softmax(torch.log(w + EPS) + dw, dim=-1)
    elif combine == "additive":
        w = w + dw
    return w[:, 0], weight_std(w[:, 1:])


def run(path, field, pts, dw, combine, grads):
    pts = pts.clone().requires_grad_()
    dw = dw.clone().requires_grad_() if combine != "none" else None
    if path == "compiled":
        wc, lw = smooth_weights_compiled(field, pts, dw, combine, EPS)
    else:
        wc, lw = torch_path(field, pts, dw, combine)
    ((wc * grads[0]).sum() + (lw * grads[1]).sum()).backward()
    return wc.detach(), lw.detach(), pts.grad, (dw.grad if dw is not None else None)


@pytest.mark.parametrize("combine", ["none", "softmax", "additive"])
def test_values_and_gradients_equal_torch_float64(combine, monkeypatch):
    monkeypatch.setattr(compiled_threads, "MIN_CHUNK", 8)  # several chunks on worker threads
    monkeypatch.setattr(torch, "get_num_threads", lambda: 3)
    field = field_with_rigid_block()
    pts, dw = scene(60)
    grads = (torch.randn(60, J, dtype=torch.float64), torch.randn(60, dtype=torch.float64))
    ref = run("torch", field, pts, dw, combine, grads)
    got = run("compiled", field, pts, dw, combine, grads)
    for name, r, g in zip(("weights", "L_w", "d points", "d dw"), ref, got, strict=True):
        if r is None:
            assert g is None
            continue
        assert torch.isfinite(g).all(), name
        assert torch.allclose(g, r, rtol=0, atol=1e-11 * max(1.0, float(r.abs().max()))), name
    # the rigid block: no spread, and no gradient through the std's infinite slope at zero
    assert (got[1][:4] == 0).all() and (ref[1][:4] == 0).all()
    # past the box's faces the lookup is clamped: no gradient along those axes
    u = (pts - field.bounds[0].double()) / (field.bounds[1] - field.bounds[0]).double()
    outside = ~((u > 0) & (u < 1))
    assert outside.any() and (got[2][outside] == 0).all()


def test_finite_differences():
    field = field_with_rigid_block()
    pts, dw = scene(12)
    pts, dw = pts[4:].clone(), dw[4:].clone()  # away from the rigid block (std's kink) and the NaN point
    pts[1, 2, 1] = 0.1
    inputs = (pts.requires_grad_(), dw.requires_grad_())
    assert torch.autograd.gradcheck(lambda p, d: smooth_weights_compiled(field, p, d, "softmax", EPS), inputs)


def test_float32_within_torch_float32_error():
    field64 = field_with_rigid_block()
    field32 = field_with_rigid_block(torch.float32)
    pts, dw = scene(200)
    grads = (torch.randn(200, J, dtype=torch.float64), torch.randn(200, dtype=torch.float64))
    ref = run("torch", field64, pts, dw, "softmax", grads)
    low = [x.float() for x in (pts, dw)]
    grads32 = [x.float() for x in grads]
    torch32 = run("torch", field32, *low, "softmax", grads32)
    comp32 = run("compiled", field32, *low, "softmax", grads32)
    for r, t, c in zip(ref, torch32, comp32, strict=True):
        assert c.dtype == torch.float32
        err_torch = float((t.double() - r).abs().max())
        err_comp = float((c.double() - r).abs().max())
        assert err_comp <= 2 * err_torch + 1e-6 * float(r.abs().max()), (err_comp, err_torch)


@pytest.fixture(scope="module")
def body():
    from plugins.body.procedural import ProceduralBody

    return ProceduralBody(segments=8)


def residual_deformer(body, compiled: bool, combine: str):
    from framework.plugins import load_plugins

    load_plugins()
    torch.manual_seed(0)  # the same F_dw for both paths
    d = REGISTRIES["deformer"].build("lbs_residual", grid_resolution=12, residual=combine, compiled_weights=compiled)
    bounds = torch.stack([body.rest_vertices.min(0).values - 0.1, body.rest_vertices.max(0).values + 0.1])
    d.bind(body, bounds)
    with torch.no_grad():
        for prm in d.mlp.parameters():
            prm.add_(torch.randn_like(prm) * 0.3)
    return d


@pytest.mark.parametrize("combine", ["softmax", "additive"])
@pytest.mark.parametrize("refining", [True, False])
def test_deformer_trains_the_same_through_either_path(body, combine, refining):
    """The deformer's outputs, L_w and the gradients of the Gaussians and of F_dw agree (float32 training)."""
    torch.manual_seed(1)
    g0 = from_body_surface(body, 300)
    T = body.bone_transforms(torch.randn(1, body.num_joints, 3) * 0.4)[0]
    results = []
    for compiled in (False, True):
        d = residual_deformer(body, compiled, combine)
        d.enabled = refining
        g = g0.replace(**{k: getattr(g0, k).clone().requires_grad_() for k in ("means", "log_scales", "quats")})
        out = d(g, T)
        loss = out.posed.means.square().sum() + out.posed.log_scales.sum() + out.aux["weight_std"].sum() * 3
        loss.backward()
        grads = [g.means.grad, g.log_scales.grad, g.quats.grad]
        grads += [p.grad if refining else torch.zeros(1) for p in d.mlp.parameters()]
        results.append((out.weights.detach(), out.aux["weight_std"].detach(), out.posed.means.detach(), grads))
    (w_t, l_t, m_t, g_t), (w_c, l_c, m_c, g_c) = results
    assert float(l_c.abs().max()) > 0.01  # L_w is not trivially zero here
    assert torch.allclose(w_c, w_t, atol=2e-6)
    assert torch.allclose(l_c, l_t, rtol=1e-4, atol=1e-6)
    assert torch.allclose(m_c, m_t, atol=1e-5)
    for a, b in zip(g_c, g_t, strict=True):
        assert torch.allclose(a, b, rtol=1e-3, atol=1e-4 * max(1.0, float(b.abs().max())))


def test_six_points_feed_the_lookup(body):
    """The compiled path reads the six L_w points the deformer builds: L_w equals the torch formula at them."""
    d = residual_deformer(body, True, "softmax")
    g = from_body_surface(body, 100)
    T = body.bone_transforms(torch.zeros(1, body.num_joints, 3))[0]
    with torch.enable_grad():
        g = g.replace(means=g.means.clone().requires_grad_())
        out = d(g, T)
        pts = torch.cat([g.means.unsqueeze(-2), six_points(g)], dim=-2).detach().double()
    field = d.field
    w = field.sample(pts.float()).double()
    _, dw = d.residual(pts.float())
    w = torch.softmax(torch.log(w + d.eps) + dw.double(), dim=-1)
    assert torch.allclose(out.aux["weight_std"].double(), weight_std(w[:, 1:]), rtol=1e-4, atol=1e-6)


def test_rejects_a_grid_that_is_no_partition_of_unity():
    vol = torch.rand(J, 4, 4, 4) * 3  # rows do not sum to one: torch's path clamps and renormalises
    field = WeightField(vol, torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    with pytest.raises(ValueError, match="sum to one"):
        smooth_weights_compiled(field, torch.zeros(2, 7, 3), None, "none", 0.0)


def _weights_std_in_child(queue) -> None:
    torch.set_num_threads(1)  # as a data-loader worker; the chunking still asks for two threads (patched)
    pts, dw = scene(40)
    queue.put(smooth_weights_compiled(field_with_rigid_block(), pts, dw, "softmax", EPS)[1].numpy())


def test_a_forked_child_does_not_wait_on_the_parents_threads(monkeypatch):
    """A data-loader worker forked after training started inherits the thread pool without its threads."""
    import multiprocessing

    monkeypatch.setattr(compiled_threads, "MIN_CHUNK", 8)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    pts, dw = scene(40)
    expected = smooth_weights_compiled(field_with_rigid_block(), pts, dw, "softmax", EPS)[1]  # the pool runs here
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_weights_std_in_child, args=(queue,))
    child.start()
    try:
        got = queue.get(timeout=120)
    finally:
        child.join(timeout=5)
        if child.is_alive():
            child.kill()
    assert torch.equal(torch.from_numpy(got), expected)

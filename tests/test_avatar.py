"""The composed avatar (corrector -> deformer -> rasterizer) and the Lightning module's stage logic."""

from __future__ import annotations

import math

import pytest
import torch

from framework.execution import COMPILED, TORCH, Execution
from framework.geometry import axis_angle_to_rotmat
from framework.model.avatar import Avatar, GaussianParams, PoseRefiner
from framework.model.gaussian_init import from_body_surface
from framework.plugins import load_plugins
from framework.registry import BODIES, CORRECTORS, DEFORMERS, RASTERIZERS
from framework.types import Cameras, FrameBatch

load_plugins()
SIZE = 48


@pytest.fixture(scope="module")
def body():
    return BODIES.build("procedural")


def _camera(w2c: torch.Tensor | None = None) -> Cameras:
    if w2c is None:  # 3 m in front of the body (which faces -y), looking at it; z up in the world
        w2c = torch.tensor([[1.0, 0, 0, 0], [0, 0, -1, 0.0], [0, 1, 0, 3.0], [0, 0, 0, 1]])
    f = SIZE * 1.2
    K = torch.tensor([[f, 0, SIZE / 2], [0, f, SIZE / 2], [0, 0, 1.0]])
    return Cameras(K[None], w2c[None], SIZE, SIZE)


def _batch(body, pose=None, root=None, cameras=None) -> FrameBatch:
    J = body.num_joints
    z = torch.zeros(1, SIZE, SIZE)
    return FrameBatch(
        image=torch.zeros(1, SIZE, SIZE, 3),
        mask=z,
        boundary=z + 1,
        cameras=cameras or _camera(),
        frame=torch.zeros(1, dtype=torch.long),
        pose=torch.zeros(1, J, 3) if pose is None else pose,
        root=torch.eye(4)[None] if root is None else root,
    )


def _avatar(body, corrector="latent", deformer="lbs_residual", n=600, execution: Execution = COMPILED) -> Avatar:
    g = from_body_surface(body, num=n, sh_degree=1, seed=0, opacity=0.6)
    corr = CORRECTORS.build(corrector)
    corr.bind(body.num_joints * 3)
    deform = DEFORMERS.build(deformer, grid_resolution=16) if deformer != "identity" else DEFORMERS.build(deformer)
    lo, hi = body.rest_vertices.min(0).values, body.rest_vertices.max(0).values
    deform.bind(body, torch.stack([lo - 0.1, hi + 0.1]))
    refiner = PoseRefiner(1, body.num_joints)
    rasterizer = RASTERIZERS.build("torch_ref")
    return Avatar(GaussianParams(g), rasterizer, corr, deform, body, refiner, execution=execution)


def test_identity_pose_with_identity_corrector_renders_the_canonical_gaussians(body):
    avatar = _avatar(body)
    out = avatar(_batch(body), sh_degree=1)
    canon = avatar.gaussians.gaussians()
    torch.testing.assert_close(out.posed.means, canon.means, atol=1e-5, rtol=0)
    direct = avatar.rasterizer.render(
        canon.means,
        canon.quats,
        canon.scales,
        canon.opacities,
        canon.sh,
        _camera(),
        sh_degree=1,
        background=avatar.background,
    )
    assert direct.alpha.max() > 0.5, "the test camera does not see the body"
    torch.testing.assert_close(out.render.rgb, direct.rgb, atol=1e-4, rtol=0)


def test_rigid_motion_of_the_whole_skeleton_equals_moving_the_camera(body):
    avatar = _avatar(body)
    with torch.no_grad():  # a non-trivial corrector and residual must not break the equivalence
        for p in list(avatar.corrector.parameters()) + list(avatar.deformer.parameters()):
            p.add_(0.02 * torch.randn_like(p))
    torch.manual_seed(0)
    pose = 0.3 * torch.randn(1, body.num_joints, 3)
    pose[:, 0] = 0
    M = torch.eye(4)
    M[:3, :3] = axis_angle_to_rotmat(torch.tensor([0.0, 0.0, math.pi / 5]))
    M[:3, 3] = torch.tensor([0.2, -0.1, 0.05])
    cam = _camera()
    moved = avatar(_batch(body, pose=pose, root=M[None]), sh_degree=1).render
    seen = avatar(_batch(body, pose=pose, cameras=Cameras(cam.K, cam.world_to_cam @ M, SIZE, SIZE)), sh_degree=1)
    assert moved.alpha.max() > 0.5
    torch.testing.assert_close(moved.rgb, seen.render.rgb, atol=2e-4, rtol=0)
    torch.testing.assert_close(moved.alpha, seen.render.alpha, atol=2e-4, rtol=0)


def test_blend_weights_are_a_partition_of_unity(body):
    avatar = _avatar(body)
    with torch.no_grad():
        for p in avatar.deformer.parameters():
            p.add_(0.5 * torch.randn_like(p))
    w = avatar.deformer.bake(avatar.gaussians.gaussians())
    assert (w >= 0).all()
    torch.testing.assert_close(w.sum(-1), torch.ones(w.shape[0]), atol=1e-5, rtol=0)


def test_baked_weights_reproduce_the_trained_render(body):
    avatar = _avatar(body)
    with torch.no_grad():
        for p in avatar.deformer.parameters():
            p.add_(0.3 * torch.randn_like(p))
    pose = 0.4 * torch.randn(1, body.num_joints, 3)
    before = avatar(_batch(body, pose=pose), sh_degree=1).render.rgb
    weights = avatar.deformer.bake(avatar.gaussians.gaussians()).detach()
    avatar.gaussians.params["skin_weights"] = torch.nn.Parameter(weights, requires_grad=False)
    avatar.deformer.mlp = None  # inference must not need F_dw any more
    after = avatar(_batch(body, pose=pose), sh_degree=1).render.rgb
    torch.testing.assert_close(after, before, atol=1e-5, rtol=0)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_inactive_sh_bands_are_skipped_without_changing_render_or_gradients(body, degree):
    """Below the full SH degree the avatar poses only the active bands, and for one camera it evaluates the colour at
    R^T d instead of rotating the coefficients; the reference poses all 16 coefficients (rotating every band) and lets
    the rasterizer evaluate them: same image, same gradient for every parameter."""
    g = from_body_surface(body, num=300, sh_degree=3, seed=0, opacity=0.6)
    g.sh[:, 1:] = 0.3 * torch.randn_like(g.sh[:, 1:])
    corr = CORRECTORS.build("latent", all_sh=True)
    corr.bind(body.num_joints * 3)
    deform = DEFORMERS.build("lbs_residual", grid_resolution=16)
    lo, hi = body.rest_vertices.min(0).values, body.rest_vertices.max(0).values
    deform.bind(body, torch.stack([lo - 0.1, hi + 0.1]))
    with torch.no_grad():
        for m in (corr.head, deform.mlp[-1]):
            m.weight.normal_(std=0.05)
    avatar = Avatar(GaussianParams(g), RASTERIZERS.build("torch_ref"), corr, deform, body)
    batch = _batch(body, pose=0.5 * torch.randn(1, body.num_joints, 3, generator=torch.Generator().manual_seed(3)))

    def render_and_grads(skip: bool) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        avatar.zero_grad(set_to_none=True)
        if skip:
            rgb = avatar(batch, sh_degree=degree).render.rgb
        else:
            _, posed, _ = avatar.pose(batch)  # all 16 coefficients, every band rotated
            assert posed.sh.shape[1] == 16
            rgb = avatar.rasterizer.render(
                posed.means, posed.quats, posed.scales, posed.opacities, posed.sh, batch.cameras, sh_degree=degree
            ).rgb
        rgb.square().sum().backward()
        return rgb.detach(), {k: p.grad.clone() for k, p in avatar.named_parameters() if p.grad is not None}

    rgb_ref, grads_ref = render_and_grads(skip=False)
    rgb, grads = render_and_grads(skip=True)
    assert rgb_ref.abs().max() > 0.1
    torch.testing.assert_close(rgb, rgb_ref, atol=1e-5, rtol=0)
    assert grads.keys() == grads_ref.keys()
    for k in grads:
        torch.testing.assert_close(grads[k], grads_ref[k], atol=1e-4, rtol=1e-4, msg=k)


def test_posed_gaussians_are_reused_for_novel_views_of_one_pose(body):
    """A second camera on the same pose reuses the posed Gaussians (the cache is keyed on the pose, not the camera)
    and still renders what that camera sees: the direct render of the posed Gaussians from it."""
    avatar = _avatar(body).eval()
    calls = []
    avatar.deformer.register_forward_hook(lambda *a: calls.append(1))
    M = torch.eye(4)
    M[:3, :3] = axis_angle_to_rotmat(torch.tensor([0.0, 0.0, 0.8]))  # orbit the camera 46 degrees about the body
    novel = Cameras(_camera().K, _camera().world_to_cam @ M, SIZE, SIZE)
    with torch.no_grad():
        a = avatar(_batch(body), sh_degree=1)
        b = avatar(_batch(body, cameras=novel), sh_degree=1)
        avatar(_batch(body, pose=0.1 * torch.ones(1, body.num_joints, 3)), sh_degree=1)
        p = b.posed
        direct = avatar.rasterizer.render(
            p.means, p.quats, p.scales, p.opacities, p.sh, novel, sh_degree=1, background=avatar.background
        )
    assert len(calls) == 2
    assert a.posed is b.posed
    assert float((a.render.rgb - b.render.rgb).abs().max()) > 0.1, "the novel camera must see a different image"
    torch.testing.assert_close(b.render.rgb, direct.rgb)


def test_stage_switch_enables_exactly_the_stage_two_parameters(body):
    from framework.lightning.callbacks import StageSwitch

    avatar = _avatar(body)

    class Trainer:
        global_step = 0

    class Module:
        pass

    module = Module()
    module.avatar = avatar
    module.log = lambda *a, **k: None
    stage2_started: list[int] = []
    module.begin_stage2 = stage2_started.append  # the module restarts its densifier schedule there
    switch = StageSwitch(stage1_steps=10)

    def grads_after_step(step: int) -> dict[str, bool]:
        Trainer.global_step = step
        switch.on_train_batch_start(Trainer, module, None, 0)
        avatar.zero_grad(set_to_none=True)
        pose = 0.2 * torch.ones(1, body.num_joints, 3)
        out = avatar(_batch(body, pose=pose), sh_degree=1)
        out.render.rgb.sum().backward()
        return {
            "gaussians": all(p.grad is not None for k, p in avatar.gaussians.params.items() if k != "latents"),
            "pose": avatar.pose_refiner.pose_residual.grad is not None,
            "joints": avatar.pose_refiner.joint_residual.grad is not None,
            "corrector": any(p.grad is not None for p in avatar.corrector.parameters()),
            "weight_mlp": any(p.grad is not None for p in avatar.deformer.parameters()),
            "latents": avatar.gaussians.params["latents"].grad is not None,
        }

    stage1 = grads_after_step(0)
    assert stage1 == {
        "gaussians": True,
        "pose": True,
        "joints": True,
        "corrector": False,
        "weight_mlp": False,
        "latents": False,
    }
    stage2 = grads_after_step(10)
    assert stage2 == {
        "gaussians": True,
        "pose": True,
        "joints": True,
        "corrector": True,
        "weight_mlp": True,
        "latents": True,
    }
    assert stage2_started == [10]


def _count_calls(monkeypatch, module, name: str) -> list[int]:
    """Wrap module.name so that each call appends to the returned list (the function still runs)."""
    calls: list[int] = []
    original = getattr(module, name)

    def counted(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(module, name, counted)
    return calls


def test_the_execution_not_the_rasterizer_chooses_the_compiled_skinning(body, monkeypatch):
    """The compiled execution (the CPU default) skins baked weights without gradients with the compiled loops, whatever
    the rasterizer: swapping the backend changes nothing else. With gradients the torch skinning runs and the posed
    means keep their graph; an avatar built with the torch execution (a GPU's code on this CPU, tools'
    --accelerator-path) never takes them. Both pose the Gaussians alike (to float32 rounding)."""
    from torch import nn

    import framework.kernels.skinning as compiled

    avatars = {}
    for name, execution in (("compiled", COMPILED), ("torch", TORCH)):
        avatar = _avatar(body, execution=execution)
        weights = avatar.deformer.bake(avatar.gaussians.gaussians()).detach()
        avatar.gaussians.params["skin_weights"] = nn.Parameter(weights.contiguous(), requires_grad=False)
        avatars[name] = avatar.eval()
    torch.manual_seed(1)
    pose = 0.4 * torch.randn(1, body.num_joints, 3)
    batch = _batch(body, pose=pose)
    calls = _count_calls(monkeypatch, compiled, "lbs_with_sh_frames_compiled")
    avatar = avatars["compiled"]
    with torch.no_grad():
        _, posed_compiled, _ = avatar.pose(batch, sh_degree=1)
    assert len(calls) == 1
    _, posed_grad, _ = avatar.pose(batch, sh_degree=1)  # gradients on: the torch path
    assert len(calls) == 1 and posed_grad.means.requires_grad
    for i, backend in enumerate(("numba", "torch_ref")):  # choosing a rasterizer leaves the skinning as it was
        avatar.rasterizer = RASTERIZERS.build(backend)
        assert avatar.rasterizer.execution is COMPILED and avatar.deformer.execution is COMPILED
        with torch.no_grad():
            avatar.pose(_batch(body, pose=(0.5 + 0.1 * i) * pose), sh_degree=1)  # a new pose: not the posed cache
        assert len(calls) == 2 + i
    with torch.no_grad():
        _, posed_torch, _ = avatars["torch"].pose(batch, sh_degree=1)
    assert len(calls) == 3
    for key in ("means", "quats", "log_scales"):
        torch.testing.assert_close(getattr(posed_compiled, key), getattr(posed_torch, key), atol=2e-5, rtol=0, msg=key)
    moved = (posed_torch.means - avatars["torch"].gaussians.gaussians().means).detach()
    assert float(moved.abs().max()) > 0.05  # the pose moved them


def test_the_compiled_execution_takes_the_compiled_view_colour(body, monkeypatch):
    """Under the compiled execution a frame gets its view colour from the compiled loops, without gradients and with
    them (training), with either rasterizer; under the torch execution from the torch path. The frames agree to
    float32 rounding (SH of degree 1 with random coefficients, a posed avatar, so the skinning frames are not the
    identity)."""
    import framework.kernels.sh_colours as compiled_sh

    avatar, torch_avatar = _avatar(body), _avatar(body, execution=TORCH)
    with torch.no_grad():
        avatar.gaussians.params["shN"].normal_(0, 0.5)
        torch_avatar.gaussians.params["shN"].copy_(avatar.gaussians.params["shN"])
    calls = _count_calls(monkeypatch, compiled_sh, "view_colour_dc_compiled")
    torch.manual_seed(3)
    batch = _batch(body, pose=0.4 * torch.randn(1, body.num_joints, 3))
    avatar.eval()
    torch_avatar.eval()
    avatar.rasterizer = RASTERIZERS.build("numba")
    with torch.no_grad():
        compiled_rgb = avatar(batch, sh_degree=1).render.rgb
    assert len(calls) == 1
    grad_rgb = avatar(batch, sh_degree=1).render.rgb  # gradients on: compiled, with its backward
    assert len(calls) == 2 and grad_rgb.requires_grad
    avatar.rasterizer = RASTERIZERS.build("torch_ref")
    with torch.no_grad():
        avatar(batch, sh_degree=1)
    assert len(calls) == 3
    with torch.no_grad():
        torch_rgb = torch_avatar(batch, sh_degree=1).render.rgb
    assert len(calls) == 3
    assert float(torch_rgb.std()) > 0.01  # the avatar is in the picture
    torch.testing.assert_close(compiled_rgb, torch_rgb, atol=1e-4, rtol=0)
    torch.testing.assert_close(compiled_rgb, grad_rgb.detach(), atol=1e-4, rtol=0)

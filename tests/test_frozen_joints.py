"""Frozen joints (`framework.model.frozen_body`): folded out of the pose input and the LBS sum without changing what
the body does in the poses the data shows."""

from __future__ import annotations

import pytest
import torch

from framework.cameras import orbit_cameras
from framework.model.avatar import Avatar, GaussianParams
from framework.model.frozen_body import FrozenJointsBody, FrozenJointsError, frozen_constants
from framework.model.gaussian_init import from_body_surface
from framework.plugins import load_plugins
from framework.registry import BODIES, CORRECTORS, DEFORMERS, RASTERIZERS
from framework.rig.fold import fold_weights
from framework.rig.lbs import six_points, weight_std
from framework.types import Cameras, FrameBatch

load_plugins()
SIZE = 40
STILL = ["hand.L", "foot.R", "head", "lowerleg.L"]


@pytest.fixture(scope="module")
def body():
    return BODIES.build("procedural")


def _cameras() -> Cameras:
    """Two views of the body, 3 m away, a quarter turn apart."""
    return orbit_cameras(torch.tensor([0.0, 0.0, 0.3]), 3.0, 0.0, 4, SIZE, SIZE, fov_deg=50.0, turns=1.0).index(
        slice(0, 2)
    )


def _avatar(body, gaussians) -> Avatar:
    deformer = DEFORMERS.build("lbs", grid_resolution=16, use_cache=False)
    lo, hi = body.rest_vertices.min(0).values, body.rest_vertices.max(0).values
    deformer.bind(body, torch.stack([lo - 0.1, hi + 0.1]))
    corrector = CORRECTORS.build("none")
    return Avatar(GaussianParams(gaussians), RASTERIZERS.build("torch_ref"), corrector, deformer, body).eval()


def _render(avatar, pose):
    root = torch.eye(4)[None]
    root[0, :3, 3] = torch.tensor([0.05, -0.02, 0.1])
    z = torch.zeros(2, SIZE, SIZE)
    batch = FrameBatch(
        image=torch.zeros(2, SIZE, SIZE, 3),
        mask=z,
        boundary=z + 1,
        cameras=_cameras(),
        frame=torch.zeros(1, dtype=torch.long),
        pose=pose[None],
        root=root,
    )
    with torch.no_grad():
        out = avatar(batch, sh_degree=0)
    return out.render.rgb, out.posed.means


def test_freezing_still_joints_leaves_renders_unchanged(body):
    """Poses that move every joint but the frozen ones render the same with the full and the folded skeleton (same
    canonical Gaussians; the folded weight field is the full one with frozen columns added to their parents)."""
    frozen = FrozenJointsBody(body, STILL)
    assert frozen.num_joints == body.num_joints - len(STILL) and frozen.num_input_joints == body.num_joints
    gaussians = from_body_surface(body, num=500, sh_degree=0, seed=1, opacity=0.8)
    full_avatar, frozen_avatar = _avatar(body, gaussians), _avatar(frozen, gaussians)
    gen = torch.Generator().manual_seed(0)
    still = [body.joint_names.index(n) for n in STILL]
    for _ in range(3):
        pose = 0.5 * torch.randn(body.num_joints, 3, generator=gen)
        pose[still] = 0.0
        rgb_full, means_full = _render(full_avatar, pose)
        rgb_frozen, means_frozen = _render(frozen_avatar, pose)
        torch.testing.assert_close(means_frozen, means_full, atol=2e-5, rtol=0)
        torch.testing.assert_close(rgb_frozen, rgb_full, atol=1e-4, rtol=0)
        assert rgb_full.abs().sum() > 10  # the body is in view
    # and the comparison can fail: move a frozen joint and the folded skeleton ignores it
    pose[body.joint_names.index("lowerleg.L")] = torch.tensor([1.2, 0.0, 0.0])
    assert (_render(full_avatar, pose)[1] - _render(frozen_avatar, pose)[1]).abs().max() > 0.05


def test_joint_frozen_at_a_bent_rotation_keeps_its_children_exact(body):
    """Freeze the left elbow bent (and the spine tilted) while the hand below it still moves: every vertex skinned to
    one joint lands where the full skeleton puts it (the kept joints' axes are turned into the re-based rest frame)."""
    constants = {"lowerarm.L": [0.0, 0.2, 0.7], "spine": [0.25, 0.0, 0.0]}
    frozen = FrozenJointsBody(body, list(constants), constants)
    gen = torch.Generator().manual_seed(3)
    pose = 0.6 * torch.randn(4, body.num_joints, 3, generator=gen)
    for name, value in constants.items():
        pose[:, body.joint_names.index(name)] = torch.tensor(value)
    full = body.posed_vertices(pose)  # [B, V, 3]
    folded = frozen.posed_vertices(frozen.input_pose(pose))
    # vertices whose weights all sit on joints with the same constant-pose transform (most of the body)
    constant_pose = torch.zeros(1, body.num_joints, 3)
    for name, value in constants.items():
        constant_pose[0, body.joint_names.index(name)] = torch.tensor(value)
    T_star = body.bone_transforms(constant_pose)[0].reshape(body.num_joints, 16)  # [J, 16]
    main = body.skin_weights.argmax(1)
    differs = (T_star[None] - T_star[main][:, None]).abs().amax(-1) > 1e-6  # [V, J]
    one_group = ((body.skin_weights > 0) & differs).sum(1) == 0
    assert one_group.sum() > 0.7 * body.skin_weights.shape[0]
    torch.testing.assert_close(folded[:, one_group], full[:, one_group], atol=1e-5, rtol=0)
    hand = (main == body.joint_names.index("hand.L")) & one_group  # below the frozen elbow, still posed
    assert hand.sum() > 50 and (full[:, hand] - body.rest_vertices[hand]).norm(dim=-1).min() > 0.05
    torch.testing.assert_close(frozen.full_pose(frozen.input_pose(pose)), pose, atol=1e-6, rtol=0)


def test_frozen_root_or_unknown_joint_is_refused(body):
    with pytest.raises(FrozenJointsError, match="root joint 'pelvis' cannot be frozen"):
        FrozenJointsBody(body, ["pelvis", "head"])
    with pytest.raises(FrozenJointsError, match=r"\['elbow'\] are not joints"):
        FrozenJointsBody(body, ["elbow"])


def test_frozen_rotation_is_the_mean_training_rotation():
    """Rotations spread symmetrically about 0.4 rad around x average to 0.4 rad around x."""
    poses = torch.zeros(5, 3, 3)
    poses[:, 1, 0] = torch.tensor([0.3, 0.35, 0.4, 0.45, 0.5])
    poses[:, 2] = torch.tensor([0.0, 0.0, 0.2])
    out = frozen_constants(poses, ["a", "b", "c"], ["b", "c"])
    assert out["b"] == pytest.approx([0.4, 0.0, 0.0], abs=1e-6)
    assert out["c"] == pytest.approx([0.0, 0.0, 0.2], abs=1e-6)


@pytest.mark.parametrize("name", ["lbs", "lbs_residual"])
def test_weight_smoothness_is_measured_over_the_whole_skeleton(body, name):
    """L_w on a body with frozen joints equals L_w of the same Gaussians on the full skeleton (reference: the deformer
    bound to the unfrozen body, zero constants so both share the rest surface), while the LBS weights are the folded
    ones. Measured on the folded weights it would be smaller: a Gaussian across the frozen knee has the same folded
    weights at all six points."""
    frozen_body = FrozenJointsBody(body, STILL)
    gaussians = from_body_surface(body, num=400, sh_degree=0, seed=2, opacity=0.8)
    gaussians = gaussians.replace(log_scales=gaussians.log_scales + 1.0)  # wide enough to straddle joints
    lo, hi = body.rest_vertices.min(0).values, body.rest_vertices.max(0).values
    bounds = torch.stack([lo - 0.1, hi + 0.1])
    deformers = {}
    for key, b in (("full", body), ("frozen", frozen_body)):
        d = DEFORMERS.build(name, grid_resolution=16, use_cache=False)
        d.bind(b, bounds)
        deformers[key] = d
    if name == "lbs_residual":  # a non-zero F_dw on the full skeleton's joints is not the same model: keep it zero
        for d in deformers.values():
            assert all(float(p.detach().abs().max()) == 0.0 for p in d.mlp[-1].parameters())
    transforms = torch.eye(4).expand(body.num_joints, 4, 4)
    means = gaussians.means.clone().requires_grad_(True)
    outs = {
        k: d(gaussians.replace(means=means), transforms[: (body if k == "full" else frozen_body).num_joints])
        for k, d in deformers.items()
    }
    std_full, std_frozen = outs["full"].aux["weight_std"], outs["frozen"].aux["weight_std"]
    assert float(std_full.detach().max()) > 0.1  # some Gaussians do straddle joints
    tol = 1e-5 if name == "lbs" else 1e-4  # lbs_residual: softmax(log(w + 1e-6)) leaks up to J * 1e-6 per weight
    torch.testing.assert_close(std_frozen, std_full, atol=tol, rtol=0)
    folded = fold_weights(outs["full"].weights, frozen_body.fold_index, frozen_body.num_joints)
    torch.testing.assert_close(outs["frozen"].weights, folded, atol=1e-5, rtol=0)
    (grad,) = torch.autograd.grad(std_frozen.sum(), means)
    (grad_full,) = torch.autograd.grad(std_full.sum(), means)
    torch.testing.assert_close(grad, grad_full, atol=1e-3, rtol=1e-3)
    # the comparison can fail: the folded weights' own spread misses the frozen boundaries
    folded_std = weight_std(
        fold_weights(
            deformers["full"].weights(torch.cat([gaussians.means[:, None], six_points(gaussians)], 1)),
            frozen_body.fold_index,
            frozen_body.num_joints,
        )[:, 1:]
    )
    assert float((std_full - folded_std).detach().max()) > 0.05


def test_weight_smoothness_with_frozen_joints_adds_the_residuals_change_on_the_kept_joints(body):
    """With F_dw on, L_w on a frozen body is std(full) + std(w) - std(grid) over the six points: the whole skeleton's
    spread plus the change F_dw makes to the kept joints' weights. Reference: the full skeleton's weights from a field
    bound to the unfrozen body, folded column by column, refined by the same F_dw, and plain float64 standard
    deviations (the deformer drops the columns of kept joints that fold no other joint, whose terms cancel)."""
    frozen_body = FrozenJointsBody(body, STILL)
    gaussians = from_body_surface(body, num=300, sh_degree=0, seed=3, opacity=0.8)
    gaussians = gaussians.replace(log_scales=gaussians.log_scales + 1.0)
    lo, hi = body.rest_vertices.min(0).values, body.rest_vertices.max(0).values
    bounds = torch.stack([lo - 0.1, hi + 0.1])
    frozen = DEFORMERS.build("lbs_residual", grid_resolution=16, use_cache=False)
    frozen.bind(frozen_body, bounds)
    full = DEFORMERS.build("lbs", grid_resolution=16, use_cache=False)
    full.bind(body, bounds)
    torch.manual_seed(0)
    with torch.no_grad():
        for p in frozen.mlp[-1].parameters():
            p.normal_(0.0, 0.5)  # a residual far from zero
    means = gaussians.means.clone().requires_grad_(True)
    moved = gaussians.replace(means=means)
    out = frozen(moved, torch.eye(4).expand(frozen_body.num_joints, 4, 4))

    six = six_points(moved)  # [N, 6, 3]
    full6 = full.weights(six).double()  # [N, 6, J_full]
    index = frozen_body.fold_index.tolist()
    grid6 = torch.stack(
        [sum(full6[..., j] for j in range(len(index)) if index[j] == k) for k in range(frozen_body.num_joints)], dim=-1
    )
    w6 = frozen.refine(six, grid6.float()).double()

    def spread(w: torch.Tensor) -> torch.Tensor:
        return w.std(dim=1, correction=0).sum(-1)

    reference = spread(full6) + spread(w6) - spread(grid6)
    assert float((spread(w6) - spread(grid6)).detach().abs().max()) > 0.01  # F_dw's change is large enough to be seen
    # tolerance: float32 fields and F_dw against float64 sums; the guard that zeroes variances under 1e-12 moves a
    # joint's term by at most 1e-6
    torch.testing.assert_close(out.aux["weight_std"].double(), reference.detach(), atol=2e-4, rtol=0)
    (grad,) = torch.autograd.grad(out.aux["weight_std"].sum(), means)
    (grad_ref,) = torch.autograd.grad(reference.sum(), means)
    torch.testing.assert_close(grad, grad_ref, atol=2e-3, rtol=2e-3)

"""Learned pruning (`framework.compaction.pruning`): blending weights against the float64 reference, renders unchanged
when only Gaussians that never show are removed, SH band energy against Monte-Carlo integration."""

from __future__ import annotations

import copy
import math

import pytest
import torch

from framework.cameras import orbit_cameras
from framework.compaction.pruning import (
    contributions,
    drop_sh_bands,
    negligible_sh_degree,
    prune_gaussians,
    sh_band_rms,
)
from framework.model.avatar import Avatar, GaussianParams
from framework.model.gaussian_init import from_body_surface
from framework.plugins import load_plugins
from framework.registry import BODIES, CORRECTORS, DEFORMERS, RASTERIZERS
from framework.splat.sh import SH_C0, sh_basis
from framework.testing.reference import reference_render
from framework.types import Cameras, FrameBatch

load_plugins()
SIZE = 40


def test_blend_weights_match_the_float64_reference():
    """Each Gaussian's T * alpha at a pixel equals d rgb / d colour of the brute-force float64 compositor (colour =
    SH_C0 * c0 + 0.5 at degree 0); over pixels and cameras, the largest, the sum of squares and the count of non-zero
    ones match: occluded, culled and overlapping Gaussians."""
    gen = torch.Generator().manual_seed(0)
    f64 = torch.float64
    N = 8
    means = 0.3 * torch.randn(N, 3, generator=gen, dtype=f64) + torch.tensor([0.0, 0.0, 3.0], dtype=f64)
    means[0] = torch.tensor([0.0, 0.0, 2.5], dtype=f64)  # a large opaque sheet in front of the others
    means[6] = torch.tensor([0.0, 0.0, 4.0], dtype=f64)  # behind the sheet
    means[7] = torch.tensor([40.0, 0.0, 3.0], dtype=f64)  # outside every view
    quats = torch.randn(N, 4, generator=gen, dtype=f64)
    scales = 0.05 + 0.2 * torch.rand(N, 3, generator=gen, dtype=f64)
    scales[0] = torch.tensor([0.8, 0.8, 0.05], dtype=f64)
    opacities = 0.3 + 0.6 * torch.rand(N, generator=gen, dtype=f64)
    opacities[0] = 0.995
    K = torch.tensor([[12.0, 0, 6], [0, 12, 5], [0, 0, 1]], dtype=f64).expand(2, 3, 3)
    w2c = torch.eye(4, dtype=f64).repeat(2, 1, 1)
    w2c[1, 0, 3] = 0.4

    def rgb_red(c0: torch.Tensor) -> torch.Tensor:
        sh = torch.zeros(N, 1, 3, dtype=f64)
        sh[:, 0, 0] = c0
        return reference_render(means, quats, scales, opacities, sh, K, w2c, 12, 10, 0)["rgb"][..., 0]

    jac = torch.autograd.functional.jacobian(rgb_red, torch.zeros(N, dtype=f64))  # [C, H, W, N]
    w = (jac / SH_C0).reshape(-1, N)  # [C * H * W, N] every pixel's weight of every Gaussian
    expected = w.amax(0)
    got = RASTERIZERS.build("torch_ref").blend_weights(means, quats, scales, opacities, Cameras(K, w2c, 12, 10))
    torch.testing.assert_close(got.max, expected, atol=1e-12, rtol=0)
    torch.testing.assert_close(got.square_sum, w.square().sum(0), atol=1e-12, rtol=0)
    torch.testing.assert_close(got.pairs, (w > 1e-14).sum(0).double(), atol=0, rtol=0)
    assert expected[7] == 0 and 0 < expected[6] < 0.05 < expected[0]  # culled, behind the sheet, the sheet
    assert got.pairs[7] == 0 and got.mean_square[7] == 0 and got.pairs[0] > 4 * got.pairs[1:7].min()
    # two sets of images summarise as one: the same cameras twice give the same largest weight, twice the sums
    both = got.add(got)
    torch.testing.assert_close(both.max, got.max, atol=0, rtol=0)
    torch.testing.assert_close(both.square_sum, 2 * got.square_sum, atol=0, rtol=0)
    torch.testing.assert_close(both.mean_square, got.mean_square, atol=1e-7, rtol=1e-6)


def _cameras() -> Cameras:
    """Two views of the body, 3 m away, a quarter turn apart."""
    return orbit_cameras(torch.tensor([0.0, 0.0, 0.3]), 3.0, 0.0, 4, SIZE, SIZE, fov_deg=50.0, turns=1.0).index(
        slice(0, 2)
    )


def _batches(body, n: int = 3) -> list[FrameBatch]:
    gen = torch.Generator().manual_seed(1)
    z = torch.zeros(2, SIZE, SIZE)
    out = []
    for i in range(n):
        pose = 0.3 * torch.randn(1, body.num_joints, 3, generator=gen)
        out.append(
            FrameBatch(
                image=torch.zeros(2, SIZE, SIZE, 3),
                mask=z,
                boundary=z + 1,
                cameras=_cameras(),
                frame=torch.tensor([i]),
                pose=pose,
                root=torch.eye(4)[None],
            )
        )
    return out


def _avatar(body, sh_degree: int = 0) -> Avatar:
    g = from_body_surface(body, num=300, sh_degree=sh_degree, seed=0, opacity=0.7)
    # two Gaussians that can never show: far outside every camera, and one too faint to reach alpha = 1/255
    g.means = torch.cat([g.means, torch.tensor([[30.0, 0.0, 0.0], [0.0, 0.0, 0.2]])])
    g.opacity_logits = torch.cat([g.opacity_logits, torch.tensor([2.0, -8.0])])
    for name in ("quats", "log_scales", "sh", "latents"):
        value = getattr(g, name)
        setattr(g, name, torch.cat([value, value[:2]]))
    deformer = DEFORMERS.build("lbs", grid_resolution=16, use_cache=False)
    lo, hi = body.rest_vertices.min(0).values, body.rest_vertices.max(0).values
    deformer.bind(body, torch.stack([lo - 0.1, hi + 0.1]))
    return Avatar(GaussianParams(g), RASTERIZERS.build("torch_ref"), CORRECTORS.build("none"), deformer, body).eval()


def _renders(avatar, batches, sh_degree: int = 0) -> torch.Tensor:
    with torch.no_grad():
        return torch.stack([avatar(b, sh_degree=sh_degree).render.rgb for b in batches])


def test_pruning_gaussians_that_never_show_leaves_renders_unchanged():
    body = BODIES.build("procedural")
    avatar, batches = _avatar(body), _batches(body)
    before = _renders(avatar, batches)
    weights = contributions(avatar, batches).max
    n = avatar.gaussians.num
    assert weights[n - 2] == 0 and weights[n - 1] == 0  # the two planted ones
    assert (weights > 0).sum() > 100
    removed = prune_gaussians(avatar.gaussians, weights > 0)
    assert removed >= 2 and avatar.gaussians.num == n - removed
    torch.testing.assert_close(_renders(avatar, batches), before, atol=1e-6, rtol=0)
    # and the comparison can fail: removing the Gaussian with the largest weight changes the image
    top = torch.ones(avatar.gaussians.num, dtype=torch.bool)
    top[int(contributions(avatar, batches).max.argmax())] = False
    prune_gaussians(avatar.gaussians, top)
    assert (_renders(avatar, batches) - before).abs().max() > 0.01


def test_sh_band_rms_matches_monte_carlo_over_directions():
    """RMS over the sphere of the colour a band adds, computed by sampling 100k directions through the SH basis."""
    gen = torch.Generator().manual_seed(2)
    sh = torch.zeros(5, 16, 3, dtype=torch.float64)
    sh[:, 1:4] = 0.3 * torch.randn(5, 3, 3, generator=gen, dtype=torch.float64)
    sh[:, 9:16] = 0.05 * torch.randn(5, 7, 3, generator=gen, dtype=torch.float64)
    basis = sh_basis(3, torch.randn(100_000, 3, generator=gen, dtype=torch.float64))  # [D, 16]
    rms = sh_band_rms(sh[:, 1:])
    for band, (lo, hi) in enumerate(((1, 4), (4, 9), (9, 16)), start=1):
        colour = torch.einsum("dk,nkc->ndc", basis[:, lo:hi], sh[:, lo:hi])  # [5, D, 3] the band's colour change
        expected = colour.pow(2).mean(1).sqrt().mean().item()
        assert rms[band - 1] == pytest.approx(expected, rel=0.02, abs=1e-12)
    assert rms[1] == 0.0 and negligible_sh_degree(sh[:, 1:], tolerance=1e-3) == 3
    assert negligible_sh_degree(sh[:, 1:], tolerance=0.05) == 1  # band 3 (~0.02) is dropped, band 1 (~0.1) kept
    assert math.isclose(negligible_sh_degree(torch.zeros(3, 15, 3)), 0)


def test_dropping_empty_sh_bands_leaves_renders_unchanged():
    body = BODIES.build("procedural")
    avatar, batches = _avatar(body, sh_degree=3), _batches(body, 2)
    gen = torch.Generator().manual_seed(4)
    with torch.no_grad():
        avatar.gaussians.params["shN"][:, :3] = 0.2 * torch.randn(avatar.gaussians.num, 3, 3, generator=gen)
    before = _renders(avatar, batches, sh_degree=3)
    degree = negligible_sh_degree(avatar.gaussians.params["shN"])
    assert degree == 1
    drop_sh_bands(avatar.gaussians, degree)
    assert avatar.gaussians.params["shN"].shape[1] == 3
    torch.testing.assert_close(_renders(avatar, batches, sh_degree=degree), before, atol=1e-6, rtol=0)


def _corrected_avatar(body, pose_weight: float) -> Avatar:
    """The pruning avatar with the paper's latent corrector; its head and pose input are set so that the correction
    is non-trivial and depends on the pose as much as `pose_weight` says (0: not at all)."""
    avatar = _avatar(body, sh_degree=1)
    corrector = CORRECTORS.build("latent")
    corrector.bind(body.num_pose_features)
    gen = torch.Generator().manual_seed(5)
    with torch.no_grad():
        corrector.head.weight.copy_(0.05 * torch.randn(corrector.head.weight.shape, generator=gen))
        corrector.head.bias.copy_(0.1 * torch.randn(corrector.head.bias.shape, generator=gen))
        corrector.pose_in.weight.mul_(pose_weight)
    avatar.corrector = corrector
    return avatar.eval()


def test_folding_a_pose_independent_corrector_leaves_renders_unchanged():
    """F_a with no pose input is one constant correction: folded into the Gaussians (latents and MLP gone), every
    pose renders as before, to float tolerance; the reference is the unfolded avatar's own render."""
    from framework.compaction.corrector_fold import fold_corrector

    body = BODIES.build("procedural")
    avatar, batches = _corrected_avatar(body, pose_weight=0.0), _batches(body)
    before = _renders(avatar, batches, sh_degree=1)
    uncorrected = _renders(_avatar(body, sh_degree=1), batches, sh_degree=1)
    assert (before - uncorrected).abs().max() > 0.02  # the correction shows, so the check below can fail
    fold = fold_corrector(avatar, batches, sh_degree=1, tolerance=1e-4)
    assert fold.folded and fold.worst < 1e-5 and fold.render_rms < 1e-5, fold
    assert "latents" not in avatar.gaussians.params and not any(True for _ in avatar.corrector.parameters())
    torch.testing.assert_close(_renders(avatar, batches, sh_degree=1), before, atol=2e-5, rtol=0)


def test_a_pose_dependent_corrector_is_measured_on_the_renders_and_kept():
    from framework.compaction.corrector_fold import fold_corrector

    body = BODIES.build("procedural")
    avatar, batches = _corrected_avatar(body, pose_weight=30.0), _batches(body)
    folded = copy.deepcopy(avatar)
    before = _renders(avatar, batches, sh_degree=1)
    fold = fold_corrector(avatar, batches, sh_degree=1, tolerance=1e-3)
    assert not fold.folded and fold.worst > 1e-3 and fold.render_rms > 1e-3, fold
    # measured against an independent render: the folded avatar's own images differ from the corrected ones by that
    assert fold_corrector(folded, batches, sh_degree=1, tolerance=1.0).folded
    with torch.no_grad():
        alpha = torch.stack(
            [torch.maximum(folded(b, sh_degree=1).render.alpha, avatar(b, sh_degree=1).render.alpha) for b in batches]
        )
    covered = (alpha >= 1 / 255).expand(-1, -1, -1, -1, 3)
    rms = float((_renders(folded, batches, sh_degree=1) - before)[covered].square().mean().sqrt())
    assert 0.1 < covered.float().mean() < 0.9 and abs(rms - fold.render_rms) < 1e-6
    # and a refused fold leaves the avatar exactly as it was
    assert "latents" in avatar.gaussians.params
    torch.testing.assert_close(_renders(avatar, batches, sh_degree=1), before, atol=0, rtol=0)


def _covered_rms_by_hand(avatar_a, avatar_b, batches, sh_degree: int) -> float:
    """RMS colour difference over pixels either avatar covers (alpha >= 1/255), computed here from the renders."""
    with torch.no_grad():
        outs = [(avatar_a(b, sh_degree=sh_degree).render, avatar_b(b, sh_degree=sh_degree).render) for b in batches]
    diff = torch.cat([(a.rgb - b.rgb)[(torch.maximum(a.alpha, b.alpha) >= 1 / 255).squeeze(-1)] for a, b in outs])
    return float(diff.square().mean().sqrt())


def test_a_partial_fold_keeps_the_mlp_on_its_rows_and_the_mean_correction_on_the_others():
    """Folding F_a for part of the Gaussians: the renders stay within the tolerance (measured here), the rows F_a
    still corrects get exactly the unfolded corrector's output, the folded rows carry the mean of its output over the
    poses in their own parameters and get no correction, and the row list survives a state-dict round trip."""
    from framework.compaction.corrector_fold import fold_corrector
    from framework.geometry import quat_normalize

    body = BODIES.build("procedural")
    avatar, batches = _corrected_avatar(body, pose_weight=30.0), _batches(body)
    original = copy.deepcopy(avatar)
    whole = fold_corrector(copy.deepcopy(avatar), batches, sh_degree=1, tolerance=1.0)
    assert whole.folded and whole.render_rms > 1e-3  # folding all of it changes the images by this much
    tolerance = 0.5 * whole.render_rms
    fold = fold_corrector(avatar, batches, sh_degree=1, tolerance=tolerance, partial=True)
    n = avatar.gaussians.num
    rows = avatar.corrector.active_rows
    assert not fold.folded and 0.05 * n <= fold.folded_gaussians < n and rows.numel() == n - fold.folded_gaussians
    assert _covered_rms_by_hand(avatar, original, batches, 1) <= tolerance
    assert abs(_covered_rms_by_hand(avatar, original, batches, 1) - fold.render_rms) < 1e-6

    folded = torch.ones(n, dtype=torch.bool)
    folded[rows] = False
    with torch.no_grad():
        canonical0, canonical = original.gaussians.gaussians(), avatar.gaussians.gaussians()
        outs0 = [original.corrector(canonical0, original.bone_transforms(b)[1]) for b in batches]
        for b, out0 in zip(batches, outs0, strict=True):
            out = avatar.corrector(canonical, avatar.bone_transforms(b)[1])
            for name in ("opacity_logits", "log_scales", "quats", "sh"):
                got, ref, canon = getattr(out, name), getattr(out0, name), getattr(canonical, name)
                torch.testing.assert_close(got[rows], ref[rows], atol=1e-6, rtol=0)  # the MLP, as before
                torch.testing.assert_close(got[folded], canon[folded], atol=0, rtol=0)  # no correction
        mean = lambda name: torch.stack([getattr(o, name) for o in outs0]).mean(0)[folded]  # noqa: E731
        torch.testing.assert_close(canonical.opacity_logits[folded], mean("opacity_logits"), atol=1e-6, rtol=0)
        torch.testing.assert_close(canonical.log_scales[folded], mean("log_scales"), atol=1e-6, rtol=0)
        torch.testing.assert_close(canonical.sh[folded], mean("sh"), atol=1e-6, rtol=0)
        unit = torch.stack([quat_normalize(o.quats) for o in outs0]).mean(0)[folded]
        torch.testing.assert_close(quat_normalize(canonical.quats[folded]), quat_normalize(unit), atol=1e-6, rtol=0)

    fresh = CORRECTORS.build("latent")
    fresh.bind(body.num_pose_features)
    fresh.load_state_dict(avatar.corrector.state_dict())
    assert torch.equal(fresh.active_rows, rows)
    old = {k: v for k, v in avatar.corrector.state_dict().items() if k != "active_rows"}  # written before it existed
    fresh.load_state_dict(old)
    assert fresh.active_rows.numel() == 0


def test_pruning_renumbers_the_rows_of_a_partially_folded_corrector():
    """Removing Gaussians that never show from a partially folded avatar leaves its renders unchanged: the rows the
    corrector still corrects follow their Gaussians (without the renumbering they would correct the wrong ones)."""
    from framework.compaction.corrector_fold import fold_corrector

    body = BODIES.build("procedural")
    avatar, batches = _corrected_avatar(body, pose_weight=30.0), _batches(body)
    with torch.no_grad():  # two more that never show, early in the rows, so that the rows after them shift
        avatar.gaussians.params["means"][[3, 7]] = torch.tensor([30.0, 0.0, 0.0])
    whole = fold_corrector(copy.deepcopy(avatar), batches, sh_degree=1, tolerance=1.0)
    fold = fold_corrector(avatar, batches, sh_degree=1, tolerance=0.5 * whole.render_rms, partial=True)
    assert 0 < fold.folded_gaussians < avatar.gaussians.num
    before = _renders(avatar, batches, sh_degree=1)
    keep = contributions(avatar, batches).max > 0
    assert (~keep).sum() >= 4 and not keep[3] and not keep[7] and int(avatar.corrector.active_rows[-1]) > 7
    prune_gaussians(avatar.gaussians, keep, avatar.corrector)
    torch.testing.assert_close(_renders(avatar, batches, sh_degree=1), before, atol=1e-6, rtol=0)


def test_pruning_within_a_tolerance_removes_faint_gaussians_and_keeps_the_renders_within_it():
    from framework.compaction.pruning import prune_within_tolerance
    from framework.compaction.render_check import RenderCheck

    body = BODIES.build("procedural")
    avatar, batches = _avatar(body), _batches(body)
    original = copy.deepcopy(avatar)
    n = avatar.gaussians.num
    check = RenderCheck.of(avatar, batches, sh_degree=0)
    weights = contributions(avatar, batches).max
    removed = prune_within_tolerance(avatar, check, weights, tolerance=0.01)
    rms = _covered_rms_by_hand(avatar, original, batches, 0)
    assert 2 < removed <= 0.9 * n and avatar.gaussians.num == n - removed and 0 < rms <= 0.01
    # a zero tolerance (bisected to a single Gaussian) removes only what never shows: the renders are the same
    exact = copy.deepcopy(original)
    assert prune_within_tolerance(exact, RenderCheck.of(exact, batches, 0), weights, tolerance=0.0, steps=n) >= 2
    torch.testing.assert_close(_renders(exact, batches), _renders(original, batches), atol=1e-6, rtol=0)

"""tools/bench_render.py's pose-path table: it must time the avatar's own novel-pose path, and its lower bound must
count F_a's arithmetic right."""

from __future__ import annotations

import pytest
import torch
from tool_module import load_tool

from framework.cameras import orbit_cameras
from framework.execution import COMPILED, TORCH, Execution
from framework.plugins import load_plugins

load_plugins()


@pytest.fixture(scope="module")
def tool():
    return load_tool("bench_render")


def _synthetic(tool, execution: Execution):
    torch.manual_seed(0)
    av = tool.synthetic_avatar("procedural", 400, "cpu", execution).eval()
    for p in av.corrector.parameters():  # a corrector that changes something (its last layer starts at zero)
        torch.nn.init.normal_(p, std=0.05)
    with torch.no_grad():  # view-dependent colour in every band (they start at zero), so each degree renders its own
        av.gaussians.params["shN"].normal_(std=0.2)
    return av


@pytest.fixture(scope="module")
def avatar(tool):
    return _synthetic(tool, COMPILED)


@pytest.mark.parametrize("degree", [3, 1])
def test_written_out_pose_path_renders_the_avatars_image(tool, avatar, degree) -> None:
    """The parts the table times are Avatar.forward's novel-pose path: same image, every SH term of the model's degree
    included. Degree 1 is a compact model's (`framework.export prune=true` drops negligible bands): it stores 4
    coefficients, so a path that asked for degree 3 could not render it at all."""
    import copy

    from framework.compaction.pruning import drop_sh_bands

    body = avatar.body
    centre = (body.rest_vertices.min(0).values + body.rest_vertices.max(0).values) / 2
    cams = orbit_cameras(centre, 3.0, 0.0, 4, 48, 48, fov_deg=40)
    pose = 0.3 * torch.randn(1, body.num_input_joints, 3, generator=torch.Generator().manual_seed(1))
    batch = tool.frame_batch(cams, pose, 1, 48, "cpu")
    calls = []
    with torch.no_grad():
        full_rgb = avatar(batch, sh_degree=3).render.rgb
        if degree < 3:
            avatar = copy.deepcopy(avatar)
            drop_sh_bands(avatar.gaussians, degree)
            assert avatar.gaussians.gaussians().sh.shape[1] == (degree + 1) ** 2
        parts = tool.pose_frame(avatar, batch, degree, lambda: calls.append(1))
        whole = avatar(batch, sh_degree=degree).render
    assert len(calls) == len(tool.POSE_PARTS)
    assert float(whole.alpha.amax()) > 0.5  # the body is in view
    torch.testing.assert_close(parts.rgb, whole.rgb, rtol=0, atol=1e-6)
    torch.testing.assert_close(parts.alpha, whole.alpha, rtol=0, atol=1e-6)
    if degree < 3:  # the bands above `degree` are gone: the image differs from the degree-3 model's
        assert float((whole.rgb - full_rgb).abs().amax()) > 1e-2


def test_corrector_flops_match_the_layer_sizes(tool, avatar) -> None:
    """FlopCounterMode's count against the closed form 2 (N (F H + (L - 2) H^2 + H O) + P H): per Gaussian the
    feature layer, the trunk and the head; the pose layer once per frame (it is shared by every Gaussian)."""
    c = avatar.corrector
    n, H, F, P = avatar.gaussians.num, c.hidden, c.feature_dim, c.num_pose_features
    O = c.head.out_features
    expected = 2 * (n * (F * H + (c.num_layers - 2) * H * H + H * O) + P * H) / 1e9
    pose_features = torch.zeros(P)
    assert tool.corrector_gflop(avatar, pose_features) == pytest.approx(expected, rel=1e-9)


def test_fixed_and_slope_fit_recovers_a_line(tool) -> None:
    """The least-squares fit against closed forms: points on t = 3 + 0.002 n give exactly (3, 0.002); four noisy
    points give the slope and intercept worked out by hand."""
    counts = [5000, 2500, 1250, 100]
    fixed, slope = tool.fit_fixed_and_slope(counts, [3.0 + 0.002 * c for c in counts])
    assert fixed == pytest.approx(3.0, abs=1e-9) and slope == pytest.approx(0.002, rel=1e-9)
    fixed, slope = tool.fit_fixed_and_slope([0, 1, 2, 3], [1.1, 1.9, 3.1, 3.9])
    assert fixed == pytest.approx(1.06) and slope == pytest.approx(0.96)  # by hand: cov 4.8, var 5


def test_subset_avatar_keeps_gaussians_and_corrected_rows(tool, avatar) -> None:
    """A subset renders the chosen Gaussians of the original: count, parameters and a partially folded corrector's
    rows renumbered to them (each kept row still points at the same Gaussian)."""
    import copy

    full = copy.deepcopy(avatar)
    n = full.gaussians.num
    full.corrector.active_rows = torch.arange(0, n, 3)  # every third Gaussian still corrected
    sub = tool.subset_avatar(full, 100, seed=1)
    assert sub.gaussians.num == 100 and full.gaussians.num == n  # the original is untouched
    means_full, means_sub = full.gaussians.params["means"], sub.gaussians.params["means"]
    index = [int((means_full == m).all(-1).nonzero()[0]) for m in means_sub]  # each kept Gaussian's original row
    assert len(set(index)) == 100
    corrected = {i for i in range(n) if i % 3 == 0}
    rows = sub.corrector.active_rows.tolist()
    assert rows and all(index[r] in corrected for r in rows)
    assert len(rows) == sum(i in corrected for i in index)


def test_operator_counts_of_the_gpu_path_show_one_host_wait_in_the_pose_path(tool) -> None:
    """`--accelerator-path`: one frame of a GPU's code on this CPU (an avatar built with the torch execution). The pose
    path may wait for the host once, in the polar decomposition's single read (framework.rig.polar); the bone
    transforms, F_a and the view colour never."""
    avatar = _synthetic(tool, TORCH)
    body = avatar.body
    centre = (body.rest_vertices.min(0).values + body.rest_vertices.max(0).values) / 2
    cams = orbit_cameras(centre, 3.0, 0.0, 4, 32, 32, fov_deg=40)
    pose = 0.3 * torch.randn(1, body.num_input_joints, 3, generator=torch.Generator().manual_seed(2))
    counts = tool.pose_frame_operators(avatar, tool.frame_batch(cams, pose, 0, 32, "cpu"), 3)
    assert list(counts) == list(tool.POSE_PARTS)
    assert all(ops > launches > 0 for ops, launches, _ in counts.values()), counts  # every part takes some views
    waits = {part: w for part, (_, _, w) in counts.items()}
    assert waits["LBS (polar, skinning)"] == 1, counts
    assert waits["bone transforms"] == waits["corrector F_a"] == waits["view colour (SH at R^T d)"] == 0, counts

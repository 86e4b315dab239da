"""Densification: clone / split / prune counts, optimizer state surgery, schedule, caps, and the canonical params."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from framework.geometry import quat_to_rotmat
from framework.model import optim_surgery as surgery
from framework.plugins import load_plugins
from framework.registry import DENSIFIERS

load_plugins()
W, H, C = 64, 48, 2
J = 5


def make_params(n: int, seed: int = 0) -> nn.ParameterDict:
    g = torch.Generator().manual_seed(seed)
    return nn.ParameterDict(
        {
            "means": nn.Parameter(torch.arange(n, dtype=torch.float32)[:, None] * torch.tensor([1.0, 0.1, 0.01])),
            "quats": nn.Parameter(torch.randn(n, 4, generator=g)),
            "log_scales": nn.Parameter(torch.full((n, 3), math.log(0.005))),  # small: clone regime (< 0.01)
            "opacity_logits": nn.Parameter(torch.full((n,), 2.0)),
            "sh": nn.Parameter(torch.randn(n, 4, 3, generator=g)),
            "latents": nn.Parameter(torch.randn(n, 9, generator=g)),
            "skin_weights": nn.Parameter(torch.softmax(torch.randn(n, J, generator=g), -1)),
        }
    )


def make_optimizers(params: nn.ParameterDict, layout: str):
    if layout == "dict":
        return {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    if layout == "single":
        return torch.optim.Adam([{"params": [p], "name": k, "lr": 1e-3} for k, p in params.items()])
    raise AssertionError(layout)


def adam_steps(params, optimizers, k: int = 2) -> None:
    for opt in surgery.optimizer_list(optimizers):
        opt.zero_grad()
    for i in range(k):
        loss = sum(
            ((p.float() - 0.3 * (i + 1)) ** 2 * torch.linspace(1, 2, p.numel()).view_as(p)).sum()
            for p in params.values()
        )
        loss.backward()
        for opt in surgery.optimizer_list(optimizers):
            opt.step()
            opt.zero_grad()


def adam_state(params, optimizers, name: str) -> dict[str, torch.Tensor]:
    for opt in surgery.optimizer_list(optimizers):
        if params[name] in opt.state:
            return opt.state[params[name]]
    raise AssertionError(f"no optimizer state for {name}")


def info_with_grad(n: int, ndc_grad: torch.Tensor, visible: torch.Tensor | None = None) -> dict:
    """means2d whose .grad holds, per Gaussian, a pixel gradient whose NDC norm per camera is `ndc_grad`."""
    means2d = torch.zeros(C, n, 2, requires_grad=True)
    g = torch.zeros(C, n, 2)
    g[..., 0] = ndc_grad / (W / 2 * C)  # x component only: |NDC grad| = ndc_grad
    means2d.grad = g
    radii = torch.ones(C, n, dtype=torch.int32) if visible is None else visible.to(torch.int32)
    return {"means2d": means2d, "radii": radii, "width": W, "height": H, "n_cameras": C}


LAYOUTS = ["dict", "single"]


@pytest.mark.parametrize("layout", LAYOUTS)
def test_clone_split_prune_counts_and_state(layout):
    n = 6
    params = make_params(n)
    with torch.no_grad():
        params["log_scales"][1] = math.log(0.05)  # large: split regime
        params["opacity_logits"][2] = -8.0  # opacity 3e-4 < 0.005: pruned
    opts = make_optimizers(params, layout)
    adam_steps(params, opts)
    old = {k: p.detach().clone() for k, p in params.items()}
    old_state = {k: {s: v.clone() for s, v in adam_state(params, opts, k).items()} for k in params}
    grads = torch.tensor([5e-4, 5e-4, 0.0, 1.5e-4, 2.5e-4, 0.0])  # 0: clone, 1: split, 3: below, 4: clone
    visible = torch.ones(C, n, dtype=torch.bool)
    visible[:, 5] = False
    dens = DENSIFIERS.build("paper", refine_start=0, refine_every=100, grad_threshold=2e-4)
    state = dens.initialize_state(scene_scale=1.0)
    info = info_with_grad(n, grads, visible)
    info["means2d"].grad[:, 5, 0] = 1.0  # huge but invisible: must not count
    dens.step_post_backward(params, opts, state, 100, info)
    assert state["last"] == {"clone": 2, "split": 1, "prune": 1}
    # order: survivors of split [0, 2, 3, 4, 5] + clones [0, 4] + split children of 1 (x2); then 2 is pruned
    survivors = [0, 3, 4, 5, 0, 4]
    n_new = 2
    for k, p in params.items():
        assert p.shape[0] == len(survivors) + n_new, k
        torch.testing.assert_close(p[: len(survivors)].detach(), old[k][survivors], msg=k)
        st = adam_state(params, opts, k)
        for s in ("exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(st[s][:4], old_state[k][s][[0, 3, 4, 5]], msg=f"{k}.{s}")
            assert (st[s][4:] == 0).all(), f"new rows of {k}.{s} must start at zero"
    # split children: scales / 1.6, other attributes copied, positions drawn around the parent
    torch.testing.assert_close(params["log_scales"][-2:].detach(), (old["log_scales"][1] - math.log(1.6)).expand(2, 3))
    for k in ("quats", "sh", "latents", "skin_weights", "opacity_logits"):
        torch.testing.assert_close(params[k][-2:].detach(), old[k][[1, 1]], msg=k)
    assert ((params["means"][-2:].detach() - old["means"][1]).norm(dim=-1) < 0.05 * 6).all()
    assert state["grad2d"].shape[0] == params["means"].shape[0] and (state["grad2d"] == 0).all()
    # training continues: an Adam step after surgery works and touches the new rows
    adam_steps(params, opts, k=1)
    assert all(torch.isfinite(p).all() for p in params.values())
    assert (adam_state(params, opts, "means")["exp_avg"][-1] != 0).any()


def test_single_optimizer_groups_follow_names():
    params = make_params(4)
    opt = make_optimizers(params, "single")
    adam_steps(params, opt)
    surgery.keep_rows(params, opt, torch.tensor([True, False, True, True]))
    for group in opt.param_groups:
        assert group["params"][0] is params[group["name"]]
        assert group["params"][0].shape[0] == 3
    assert len(opt.state) == len(params)


def test_lightning_optimizer_wrapper():
    from lightning.pytorch.core.optimizer import LightningOptimizer

    params = make_params(4)
    opt = make_optimizers(params, "single")
    adam_steps(params, opt)
    old = adam_state(params, opt, "latents")["exp_avg"].clone()
    wrapped = LightningOptimizer(opt)
    assert surgery.optimizer_list([wrapped, opt]) == [opt]
    surgery.keep_rows(params, wrapped, torch.tensor([3, 1]))
    torch.testing.assert_close(adam_state(params, opt, "latents")["exp_avg"], old[[3, 1]])
    assert all(g["params"][0] is params[g["name"]] for g in opt.param_groups)


def test_shared_optimizer_in_dict_and_amsgrad():
    """Several keys mapped to one optimizer, with amsgrad's extra per-row state."""
    params = make_params(5)
    opt = torch.optim.Adam(list(params.values()), lr=1e-2, amsgrad=True)
    adam_steps(params, {k: opt for k in params})
    before = adam_state(params, opt, "sh")["max_exp_avg_sq"].clone()
    step_before = adam_state(params, opt, "sh")["step"].clone()
    surgery.append_rows(params, {k: opt for k in params}, {k: p.detach()[:2] for k, p in params.items()})
    st = adam_state(params, opt, "sh")
    torch.testing.assert_close(st["max_exp_avg_sq"][:5], before)
    assert (st["max_exp_avg_sq"][5:] == 0).all() and st["step"] == step_before
    adam_steps(params, opt, k=1)


def test_surgery_errors():
    params = make_params(3)
    params["bad"] = nn.Parameter(torch.zeros(4))
    with pytest.raises(ValueError, match="same leading dimension"):
        surgery.num_rows(params)
    params = make_params(3)
    opts = {k: torch.optim.Adam([p]) for k, p in params.items() if k != "sh"}
    with pytest.raises(ValueError, match="'sh' requires grad but no optimizer holds it"):
        surgery.keep_rows(params, opts, torch.tensor([0, 1]))
    with pytest.raises(ValueError, match="missing"):
        surgery.append_rows(make_params(2), None, {"means": torch.zeros(1, 3)})


def test_split_samples_follow_the_gaussian():
    """Children of many identical Gaussians have covariance R S^2 R^T (independent of the sampler's formula)."""
    torch.manual_seed(0)
    n = 4000
    params = make_params(n)
    scales = torch.tensor([0.3, 0.1, 0.02])
    q = torch.tensor([0.9, 0.2, -0.3, 0.25])
    with torch.no_grad():
        params["means"].zero_()
        params["log_scales"].copy_(scales.log().expand(n, 3))
        params["quats"].copy_(q.expand(n, 4))
    dens = DENSIFIERS.build("paper")
    state = dens.initialize_state()
    dens.split(params, None, state, torch.ones(n, dtype=torch.bool))
    x = params["means"].detach().double()
    assert x.shape == (2 * n, 3)
    R = quat_to_rotmat(q).double()
    cov = R @ torch.diag(scales.double() ** 2) @ R.T
    torch.testing.assert_close(x.T @ x / x.shape[0], cov, atol=2.5e-3, rtol=0.08)


def test_opacity_reset_schedule():
    dens = DENSIFIERS.build("paper", refine_stop=30_000)
    state = dens.initialize_state()
    resets = [s for s in range(0, 30_000, 100) if dens.is_reset_step(s, state)]
    assert resets == [3000, 9000, 15000, 21000, 27000]  # a single-stage run: 3000, then every 6000
    dens.restart_schedule(state, 5000)  # stage 2 starts at 5000: the paper's "every 6000 iterations in stage 2"
    assert [s for s in range(0, 30_000, 100) if dens.is_reset_step(s, state)] == [3000, 11000, 17000, 23000, 29000]
    short = DENSIFIERS.build("paper", refine_stop=15_000)  # resets end with densification
    state = short.initialize_state()
    short.restart_schedule(state, 5000)
    assert [s for s in range(0, 30_000, 100) if short.is_reset_step(s, state)] == [3000, 11000]


def test_reset_restart_fixes_the_stage2_count_whatever_the_stage_switch():
    """reset_restart (paper_full: stage 2's start in the schedule) anchors the resets after the first, so a run whose
    stage switch is elsewhere (the "w/o first stage" row: at 0, never reported) resets at the same steps."""
    dens = DENSIFIERS.build("paper", refine_stop=15_000, reset_restart=5000)
    for reported in (None, 0, 5000, 8000):
        state = dens.initialize_state()
        if reported is not None:
            dens.restart_schedule(state, reported)
        assert [s for s in range(0, 30_000, 100) if dens.is_reset_step(s, state)] == [3000, 11000], reported
    with pytest.raises(ValueError, match="reset_restart"):
        DENSIFIERS.build("paper", reset_restart=-1)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_opacity_reset_clamps_and_zeroes_state(layout):
    n = 4
    params = make_params(n)
    with torch.no_grad():
        params["opacity_logits"].copy_(torch.tensor([30.0, 0.0, -3.0, -30.0]))
    opts = make_optimizers(params, layout)
    adam_steps(params, opts)
    other = adam_state(params, opts, "means")["exp_avg"].clone()
    logits = params["opacity_logits"].detach().clone()
    dens = DENSIFIERS.build("paper", refine_start=10_000)
    state = dens.initialize_state()
    dens.step_post_backward(params, opts, state, 3000, info_with_grad(n, torch.zeros(n)))
    assert state["last"].get("reset") is True
    expected = torch.minimum(logits, torch.tensor(math.log(0.01 / 0.99)))
    torch.testing.assert_close(params["opacity_logits"].detach(), expected)
    assert torch.sigmoid(params["opacity_logits"]).max().item() == pytest.approx(0.01, rel=1e-5)
    st = adam_state(params, opts, "opacity_logits")
    assert (st["exp_avg"] == 0).all() and (st["exp_avg_sq"] == 0).all()
    torch.testing.assert_close(adam_state(params, opts, "means")["exp_avg"], other)  # others untouched
    dens.step_post_backward(params, opts, state, 3100, info_with_grad(n, torch.zeros(n)))
    assert "reset" not in state["last"]


def test_uses_canonical_params_and_gradient_of_total_loss():
    """Decisions read the canonical scales/opacities even when the corrected (rendered) ones differ, and the
    accumulated gradient is that of the summed RGB + alpha loss through means2d."""
    n = 3
    params = make_params(n)
    with torch.no_grad():
        params["opacity_logits"][2] = -8.0  # canonical: prunable
    delta_log_scale = torch.full((n, 3), 3.0)  # corrector makes every rendered Gaussian 20x larger
    delta_opacity = torch.tensor([0.0, 0.0, 20.0])  # ... and Gaussian 2 opaque
    opts = make_optimizers(params, "dict")
    dens = DENSIFIERS.build("paper", refine_start=0, grad_threshold=2e-4)
    state = dens.initialize_state()
    # a stand-in render: means2d from the means, an "rgb" and an "alpha" term both depending on it
    means2d = (params["means"][:, :2] * 10.0).unsqueeze(0).expand(C, n, 2)  # [C, N, 2], non-leaf
    corrected_opacity = torch.sigmoid(params["opacity_logits"] + delta_opacity)
    corrected_scale = (params["log_scales"] + delta_log_scale).exp().amax(-1)
    info = {"means2d": means2d, "radii": torch.ones(C, n), "width": W, "height": H, "n_cameras": C}
    dens.step_pre_backward(params, opts, state, 100, info)
    weights = torch.tensor([1e-5, 1e-6, 0.0])
    rgb_loss = (means2d[..., 0].sum(0) * weights * corrected_opacity * corrected_scale).sum()
    alpha_loss = (means2d[..., 0].sum(0) * weights).sum()
    (rgb_loss + alpha_loss).backward()
    # per camera d(total)/d means2d_x = w * (opacity * scale + 1): the rgb part plus the alpha part
    expected_ndc = (weights * (corrected_opacity * corrected_scale + 1.0)).detach() * W / 2 * C
    dens.accumulate(params, state, info)
    torch.testing.assert_close(state["grad2d"] / state["count"], expected_ndc)
    assert expected_ndc[0] > 2e-4 > expected_ndc[1]
    state["grad2d"].zero_()
    state["count"].zero_()
    dens.step_post_backward(params, opts, state, 100, info)
    # canonical max scale 0.005 <= 0.01 -> clone (rendered 0.1 would have meant split); canonical opacity -> prune
    assert state["last"] == {"clone": 1, "split": 0, "prune": 1}
    assert params["means"].shape[0] == 3


def test_max_gaussians_cap_prefers_high_gradients():
    n = 10
    params = make_params(n)
    with torch.no_grad():
        params["log_scales"][5:] = math.log(0.05)  # 5..9 split (+1 each), 0..4 clone (+1 each)
    opts = make_optimizers(params, "dict")
    grads = torch.tensor([3e-4, 9e-4, 4e-4, 1e-3, 5e-4, 8e-4, 2.5e-4, 6e-4, 7e-4, 1e-5])
    dens = DENSIFIERS.build("paper", refine_start=0, max_gaussians=14, prune_opacity=0.0)
    state = dens.initialize_state()
    dens.step_post_backward(params, opts, state, 100, info_with_grad(n, grads))
    assert params["means"].shape[0] == 14
    # the four largest gradients: 3 (1e-3, clone), 1 (9e-4, clone), 5 (8e-4, split), 8 (7e-4, split)
    assert state["last"] == {"clone": 2, "split": 2, "prune": 0}
    kept_ids = params["means"][:, 0].detach()
    for i in (0, 2, 4, 6, 7):  # untouched originals still there once
        assert (kept_ids == float(i)).sum() == 1
    for i in (1, 3):
        assert (kept_ids == float(i)).sum() == 2
    # at the cap nothing grows
    dens.step_post_backward(params, opts, state, 200, info_with_grad(14, torch.full((14,), 1e-2)))
    assert params["means"].shape[0] == 14 and state["last"]["clone"] + state["last"]["split"] == 0


def test_refine_schedule_and_large_pruning():
    n = 4
    params = make_params(n)
    with torch.no_grad():
        params["log_scales"][0] = math.log(0.5)  # larger than prune_scale3d * scene_scale = 0.1
    opts = make_optimizers(params, "dict")
    dens = DENSIFIERS.build("paper", refine_start=500, refine_stop=15_000, grad_threshold=1.0)
    state = dens.initialize_state()
    for step in (500, 550):  # at refine_start (exclusive) and off the refine_every grid: nothing happens
        dens.step_post_backward(params, opts, state, step, info_with_grad(n, torch.zeros(n)))
        assert "prune" not in state["last"]
    dens.step_post_backward(params, opts, state, 600, info_with_grad(n, torch.zeros(n)))
    assert state["last"]["prune"] == 0  # big ones survive before the first reset
    dens.step_post_backward(params, opts, state, 3100, info_with_grad(n, torch.zeros(n)))
    assert state["last"]["prune"] == 1 and params["means"].shape[0] == 3
    dens.step_post_backward(params, opts, state, 15_000, info_with_grad(3, torch.full((3,), 10.0)))
    assert state["last"] == {} and params["means"].shape[0] == 3  # past refine_stop


def test_accumulation_over_steps_and_cameras():
    n = 3
    params = make_params(n)
    dens = DENSIFIERS.build("paper", refine_start=10_000)
    state = dens.initialize_state()
    visible = torch.tensor([[True, True, False], [True, False, False]])
    dens.step_post_backward(params, None, state, 1, info_with_grad(n, torch.tensor([1.0, 2.0, 3.0]), visible))
    dens.step_post_backward(params, None, state, 2, info_with_grad(n, torch.tensor([3.0, 2.0, 3.0])))
    torch.testing.assert_close(state["count"], torch.tensor([4.0, 3.0, 2.0]))
    torch.testing.assert_close(state["grad2d"], torch.tensor([2 * 1.0 + 2 * 3.0, 2.0 + 2 * 2.0, 2 * 3.0]))


def test_empty_and_none():
    params = make_params(0)
    opts = make_optimizers(params, "dict")
    dens = DENSIFIERS.build("paper", refine_start=0)
    state = dens.initialize_state()
    dens.step_post_backward(params, opts, state, 100, info_with_grad(0, torch.zeros(0)))
    dens.step_post_backward(params, opts, state, 3000, info_with_grad(0, torch.zeros(0)))
    assert params["means"].shape[0] == 0
    params = make_params(3)
    none = DENSIFIERS.build("none")
    st = none.initialize_state(2.0)
    none.step_pre_backward(params, None, st, 3000, info_with_grad(3, torch.ones(3)))
    none.step_post_backward(params, None, st, 3000, info_with_grad(3, torch.ones(3)))
    assert params["means"].shape[0] == 3 and params["opacity_logits"].detach().eq(2.0).all()


def test_missing_keys_and_mismatched_means2d():
    dens = DENSIFIERS.build("paper")
    state = dens.initialize_state()
    params = make_params(3)
    del params["quats"]
    with pytest.raises(ValueError, match="lack \\['quats'\\]"):
        dens.step_post_backward(params, None, state, 1, info_with_grad(3, torch.zeros(3)))
    with pytest.raises(ValueError, match="means2d'\\] has 4 Gaussians, params have 3"):
        dens.step_post_backward(make_params(3), None, state, 1, info_with_grad(4, torch.zeros(4)))


def test_densifier_configs():
    from pathlib import Path

    from omegaconf import OmegaConf

    conf = Path(__file__).resolve().parents[1] / "conf" / "densifier"
    for name in ("paper", "none"):
        cfg = OmegaConf.to_container(OmegaConf.load(conf / f"{name}.yaml"))
        assert cfg.pop("name") == name
        assert DENSIFIERS.build(name, **cfg).registry_name == name

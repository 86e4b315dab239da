"""Each Table 4 row means what the paper means: what the row changes from paper_full, what its loss sees, the
opacity-reset schedule every profile really runs, and that L_w costs nothing when its weight is 0."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from framework.build import build_component
from framework.model.losses import CompositeLoss
from framework.plugins import load_plugins
from framework.types import Cameras, FrameBatch, RenderOutput

load_plugins()


def composed(*overrides: str) -> dict:
    with initialize_config_module("framework.conf", version_base="1.3"):
        cfg = compose("train", overrides=list(overrides), return_hydra_config=True)
    data = OmegaConf.to_container(cfg, resolve=False)
    data.pop("hydra")
    data["paths"]["output_dir"] = "unused"
    job = OmegaConf.create(data)
    return OmegaConf.to_container(job, resolve=True)  # type: ignore[return-value]


def changed_groups(row: str) -> set[str]:
    full = composed("+experiment=paper_full")
    cfg = composed(f"+experiment={row}")
    return {k for k in set(cfg) | set(full) if cfg.get(k) != full.get(k)} - {"task_name"}


def _render_and_batch(seed: int = 0, h: int = 24, w: int = 20) -> tuple[RenderOutput, FrameBatch]:
    g = torch.Generator().manual_seed(seed)
    mask = torch.zeros(1, h, w)
    mask[:, 5:19, 6:15] = 1.0
    boundary = torch.ones(1, h, w)
    boundary[:, 3:21, 4:17] = 0.0
    boundary[:, 7:17, 8:13] = 1.0
    image = torch.rand(1, h, w, 3, generator=g)
    cams = Cameras(torch.eye(3)[None], torch.eye(4)[None], w, h)
    batch = FrameBatch(image=image, mask=mask, boundary=boundary, cameras=cams, frame=torch.zeros(1, dtype=torch.long))
    render = RenderOutput(rgb=torch.rand(1, h, w, 3, generator=g), alpha=torch.rand(1, h, w, 1, generator=g),
                          depth=None, means2d=torch.zeros(1, 0, 2), radii=torch.zeros(1, 0))  # fmt: skip
    return render, batch


def test_foreground_only_row_sees_nothing_outside_the_human_mask():
    """The paper's "only foreground" row: image loss (L1 and D-SSIM) on the human mask only, and no alpha loss, so
    whatever is rendered outside the mask (colour or opacity) costs nothing."""
    terms = composed("+experiment=foreground_only_loss")["loss"]["terms"]
    loss = CompositeLoss(terms)
    assert "alpha" not in loss.terms
    render, batch = _render_and_batch()
    inside = batch.mask[..., None].bool()
    agrees_inside = RenderOutput(rgb=torch.where(inside, batch.image, render.rgb), alpha=render.alpha, depth=None,
                                 means2d=render.means2d, radii=render.radii)  # fmt: skip
    total, values = loss(agrees_inside, batch, {})
    assert total.item() == pytest.approx(0.0, abs=1e-6), values
    differs_inside = RenderOutput(rgb=torch.where(inside, 1 - batch.image, render.rgb), alpha=render.alpha,
                                  depth=None, means2d=render.means2d, radii=render.radii)  # fmt: skip
    assert loss(differs_inside, batch, {})[0].item() > 1e-3
    assert changed_groups("foreground_only_loss") == {"loss"}


def test_simple_3dgs_lbs_drops_exactly_the_corrector_and_joint_optimisation():
    """The paper: "simple 3DGS+LBS" omits F_a and the joint optimisation; everything else is paper_full's."""
    assert changed_groups("simple_3dgs_lbs") == {"corrector", "pose_refine"}
    cfg = composed("+experiment=simple_3dgs_lbs")
    assert cfg["corrector"]["name"] == "none" and cfg["pose_refine"]["enabled"] is False
    # the stripped-down variant keeps its own name and stays out of Table 4
    plain = composed("+experiment=plain_3dgs_lbs")
    assert plain["deformer"]["name"] == "lbs" and plain["stages"]["stage1_steps"] == 0
    sweep = (
        OmegaConf.load(__import__("pathlib").Path(__file__).resolve().parents[1] / "sweeps" / "ablations.yaml")
        .hydra.sweeper.params["+experiment"]
        .replace("\n", "")
    )
    assert "plain_3dgs_lbs" not in sweep.split(",")


@pytest.mark.parametrize(
    ("experiment", "path", "value"),
    [
        ("paper_full_alpha_l2", ("loss", "terms", "alpha", "norm"), "l2"),
        ("paper_full_additive_weights", ("deformer", "residual"), "additive"),
        ("paper_full_rigid_centres", ("deformer", "centres"), "rigid"),
    ],
)
def test_each_paper_form_experiment_changes_one_key(experiment: str, path: tuple[str, ...], value: str):
    """paper_full uses our forms; each paper-form experiment switches exactly one of them to the paper's."""
    full, cfg = composed("+experiment=paper_full"), composed(f"+experiment={experiment}")
    assert changed_groups(experiment) == {path[0]}
    ours, theirs = full, cfg
    for key in path:
        ours, theirs = ours[key], theirs[key]
    assert theirs == value and ours != value
    cfg[path[0]] = full[path[0]]
    assert {k: v for k, v in cfg.items() if k != "task_name"} == {k: v for k, v in full.items() if k != "task_name"}


def _reset_steps(profile: str) -> tuple[list[int], dict]:
    """Opacity resets over a whole run of paper_full at `profile`, with the real stage-switch callback driving the
    densifier's schedule (as the trainer does, one call per training batch)."""
    from framework.lightning.callbacks import StageSwitch
    from framework.lightning.module import SplatModule

    cfg = composed("+experiment=paper_full", f"profile={profile}")
    densifier = build_component("densifier", cfg["densifier"])
    part = SimpleNamespace(enabled=False)
    module = SimpleNamespace(densifier=densifier, densifier_state=densifier.initialize_state(),
                             avatar=SimpleNamespace(corrector=part, deformer=SimpleNamespace(enabled=False)),
                             log=lambda *a, **k: None)  # fmt: skip
    module.begin_stage2 = lambda step: SplatModule.begin_stage2(module, step)
    switch = StageSwitch(int(cfg["stages"]["stage1_steps"]))
    trainer = SimpleNamespace(global_step=0)
    switch.on_train_start(trainer, module)
    resets = []
    for step in range(int(cfg["trainer"]["max_steps"])):
        trainer.global_step = step
        switch.on_train_batch_start(trainer, module, None, step)
        if densifier.is_reset_step(step, module.densifier_state):
            resets.append(step)
    return resets, cfg


@pytest.mark.parametrize(
    ("profile", "expected"),
    [
        # 30k steps, stage 2 from 5000, densification until 15000: 3000 (stage 1), 5000 + 6000 (stage 2)
        ("gpu", [3000, 11000]),
        # 4000 steps = 2/15 of the paper's length: reset at 400, then every 800 after stage 2 starts at 1000,
        # while densifying (until 3000)
        ("cpu", [400, 1800, 2600]),
    ],
)
def test_opacity_reset_schedule_of_each_profile(profile: str, expected: list[int]):
    resets, cfg = _reset_steps(profile)
    assert resets == expected
    stage2 = int(cfg["stages"]["stage1_steps"])
    assert [s for s in resets if s < stage2] == [resets[0]], "one reset in stage 1"


def test_ablation_profile_reset_schedule_follows_its_step_count():
    resets, cfg = _reset_steps("ablation")
    steps, stage2 = int(cfg["trainer"]["max_steps"]), int(cfg["stages"]["stage1_steps"])
    scale = steps / 30000
    assert resets[0] == round(3000 * scale) < stage2
    gaps = [b - a for a, b in zip(resets[1:-1], resets[2:], strict=False)]
    assert resets[1] - stage2 == round(6000 * scale) and all(g == round(6000 * scale) for g in gaps)


def _tiny_module(experiment: str):
    from framework.lightning.module import SplatModule

    cfg = composed(f"+experiment={experiment}", "body=procedural", "deformer.grid_resolution=8", "gaussians.num=200",
                   "rasterizer=torch_ref")  # fmt: skip
    data_info = {"bounds": [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], "num_frames_total": 2, "body_name": "procedural",
                 "num_joints": 17}  # fmt: skip
    return SplatModule(cfg, data_info)


def _batch(size: int = 16) -> FrameBatch:
    w2c = torch.tensor([[1.0, 0, 0, 0], [0, 0, -1, 0.0], [0, 1, 0, 3.0], [0, 0, 0, 1]])
    K = torch.tensor([[20.0, 0, size / 2], [0, 20.0, size / 2], [0, 0, 1]])
    z = torch.zeros(1, size, size)
    return FrameBatch(image=torch.zeros(1, size, size, 3), mask=z, boundary=z + 1,
                      cameras=Cameras(K[None], w2c[None], size, size), frame=torch.zeros(1, dtype=torch.long),
                      pose=torch.zeros(1, 17, 3), root=torch.eye(4)[None])  # fmt: skip


def test_weight_std_is_not_computed_when_its_loss_weight_is_zero(tmp_path, monkeypatch):
    """L_w needs the blend weights at six extra points per Gaussian; with weight 0 (`no_weight_std_loss`) the
    deformer must not compute them at all."""
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(tmp_path))
    for experiment, wanted in (("paper_full", True), ("no_weight_std_loss", False)):
        module = _tiny_module(experiment)
        deformer = module.avatar.deformer
        sampled, smoothed = [], []  # points given to the field lookup alone / to the lookup with L_w
        for name, calls in (("weights", sampled), ("smooth_weights", smoothed)):
            original = getattr(deformer, name)
            monkeypatch.setattr(deformer, name, lambda p, _o=original, _s=calls: _s.append(p.shape[:-1]) or _o(p))
        out = module.render_batch(_batch(), step=0)
        n = module.avatar.gaussians.num
        assert ("weight_std" in out.aux) is wanted, experiment
        if wanted:  # the compiled path (the CPU default) looks the seven points up without calling `weights`
            assert smoothed == [(n, 7)] and sampled in ([], [(n, 7)]), experiment
        else:
            assert smoothed == [] and sampled == [(n,)], experiment


def test_paper_forms_sweep_lists_paper_full_and_each_form():
    from pathlib import Path

    sweep = OmegaConf.load(Path(__file__).resolve().parents[1] / "sweeps" / "paper_forms.yaml").hydra.sweeper.params
    assert str(sweep["+experiment"]).split(",") == ["paper_full", "paper_full_alpha_l2", "paper_full_additive_weights",
                                                    "paper_full_rigid_centres"]  # fmt: skip
    assert str(sweep.seed) == "0,1,2" and sweep.data == "synthetic_studio_realistic"

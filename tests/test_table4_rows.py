"""Each Table 4 row means what the paper means: the exact config keys each row changes from paper_full, what its
loss sees, the milestones of the one schedule (fractions of the run, moved together by `profile.max_steps`), the
opacity resets every profile really runs, and that L_w costs nothing when its weight is 0."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from framework.build import build_component
from framework.config_resolvers import steps
from framework.data.boundary import scaled_half_width
from framework.model.losses import CompositeLoss
from framework.plugins import load_plugins
from framework.types import Cameras, FrameBatch, RenderOutput
from tests.helpers.config_keys import flat

load_plugins()
ROOT = Path(__file__).resolve().parents[1]


def composed(*overrides: str) -> dict:
    with initialize_config_module("framework.conf", version_base="1.3"):
        cfg = compose("train", overrides=list(overrides), return_hydra_config=True)
    data = OmegaConf.to_container(cfg, resolve=False)
    data.pop("hydra")
    data["paths"]["output_dir"] = "unused"
    job = OmegaConf.create(data)
    return OmegaConf.to_container(job, resolve=True)  # type: ignore[return-value]


def changed_keys(experiment: str, *overrides: str) -> dict[str, tuple[object, object]]:
    """{dotted key: (paper_full's value, the experiment's)} for every resolved key that differs (absent keys too)."""
    full = flat(composed("+experiment=paper_full", *overrides))
    cfg = flat(composed(f"+experiment={experiment}", *overrides))
    return {
        k: (full.get(k, "<absent>"), cfg.get(k, "<absent>"))
        for k in full.keys() | cfg.keys()
        if full.get(k, "<absent>") != cfg.get(k, "<absent>") and k != "task_name"
    }


def changed_groups(row: str) -> set[str]:
    return {k.split(".")[0] for k in changed_keys(row)}


CORRECTOR_OFF = {
    "corrector.name": ("latent", "none"),
    "corrector.hidden": (128, "<absent>"),
    "corrector.layers": (4, "<absent>"),
    "corrector.all_sh": (False, "<absent>"),
}
#: Table 4 row -> exactly the resolved keys it changes from paper_full, with (paper_full's value, the row's)
TABLE4_ROWS: dict[str, dict[str, tuple[object, object]]] = {
    "simple_3dgs_lbs": {**CORRECTOR_OFF, "pose_refine.enabled": (True, False)},
    "posenc_instead_of_latent": {
        "corrector.name": ("latent", "posenc"),
        "corrector.num_freqs": ("<absent>", 3),
        "corrector.extent": ("<absent>", 1.0),
    },
    "foreground_only_loss": {
        "loss.terms.l1.foreground_only": ("<absent>", True),
        "loss.terms.dssim.foreground_only": ("<absent>", True),
        "loss.terms.alpha.weight": (10.0, 0.0),
    },
    "all_sh_correction": {"corrector.all_sh": (False, True), "corrector.sh_degree": ("<absent>", 3)},
    "no_first_stage": {"stages.stage1_steps": (1000, 0)},
    "no_joint_optimisation": {"pose_refine.enabled": (True, False)},
    # M_b leaves both terms that use it: eq. 7 has it inside L_alpha as well as in the L1 term
    "no_boundary_mask": {"loss.terms.l1.boundary": (True, False), "loss.terms.alpha.boundary": (True, False)},
    "no_corrector": CORRECTOR_OFF,
    "no_alpha_loss": {"loss.terms.alpha.weight": (10.0, 0.0)},
    "no_weight_std_loss": {"loss.terms.weight_std.weight": (0.2, 0.0)},
}
#: the project's own forms, each switched on alone against paper_full (sweeps/paper_forms.yaml)
OUR_FORMS: dict[str, dict[str, tuple[object, object]]] = {
    "paper_full_softmax_weights": {"deformer.residual": ("additive", "softmax")},
    "paper_full_blended_centres": {"deformer.centres": ("rigid", "blended")},
    "paper_full_alpha_l1": {"loss.terms.alpha.norm": ("mse", "l1")},
    "paper_full_half_dssim": {"loss.terms.dssim.form": ("full", "half")},
    "paper_full_fixed_band": {"data.boundary_ref_side": (512, None)},
}


def _header(experiment: str) -> str:
    text = (ROOT / "conf" / "experiment" / f"{experiment}.yaml").read_text()
    return " ".join(line.lstrip("# ") for line in text.splitlines() if line.startswith("#"))


def _sweep_list(name: str) -> list[str]:
    params = OmegaConf.load(ROOT / "sweeps" / f"{name}.yaml").hydra.sweeper.params
    return [e.strip() for e in str(params["+experiment"]).replace("\n", "").split(",")]


@pytest.mark.parametrize("row", sorted(TABLE4_ROWS))
def test_each_table4_row_changes_exactly_its_keys(row: str):
    """At the CPU profile, and at another length, where the schedule's steps differ (no row may move a milestone)."""
    assert changed_keys(row) == TABLE4_ROWS[row]
    other = changed_keys(row, "profile=gpu", "profile.max_steps=12000")
    expected = dict(TABLE4_ROWS[row])
    if row == "no_first_stage":
        expected["stages.stage1_steps"] = (2000, 0)
    assert other == expected
    assert "Table 4 ablation" in _header(row)
    assert row in _sweep_list("ablations")


def test_paper_full_is_the_papers_forms():
    cfg = flat(composed("+experiment=paper_full"))
    assert cfg["deformer.name"] == "lbs_residual" and cfg["deformer.residual"] == "additive"
    assert cfg["deformer.centres"] == "rigid"
    assert cfg["loss.terms.dssim.form"] == "full" and cfg["loss.terms.alpha.norm"] == "mse"
    assert cfg["loss.terms.l1.boundary"] is True and cfg["loss.terms.alpha.boundary"] is True
    assert cfg["loss.terms.weight_std.reduction"] == "mean"
    assert (cfg["data.boundary_px"], cfg["data.boundary_ref_side"]) == (5, 512)
    weights = {k: cfg[f"loss.terms.{k}.weight"] for k in ("l1", "alpha", "weight_std", "dssim", "lpips")}
    assert weights == {"l1": 0.8, "alpha": 10.0, "weight_std": 0.2, "dssim": 0.2, "lpips": 0.0}
    assert sorted(_sweep_list("ablations")) == sorted(["paper_full", *TABLE4_ROWS])


@pytest.mark.parametrize("experiment", sorted(OUR_FORMS))
def test_each_of_our_forms_changes_one_key(experiment: str):
    """paper_full uses the paper's forms; each paper_full_<form> switches exactly one of them to the project's."""
    assert changed_keys(experiment) == OUR_FORMS[experiment]
    assert "Not a Table 4 row" in _header(experiment)


def test_splatrig_full_is_all_of_our_forms_together():
    union = {k: v for form in OUR_FORMS.values() for k, v in form.items()}
    assert changed_keys("splatrig_full") == union
    assert _sweep_list("paper_forms") == ["paper_full", *OUR_FORMS, "splatrig_full", "splatrig_deformer"]
    sweep = OmegaConf.load(ROOT / "sweeps" / "paper_forms.yaml").hydra.sweeper.params
    assert str(sweep.seed) == "0,1,2" and sweep.data == "synthetic_studio_realistic"


def test_splatrig_deformer_is_our_two_lbs_forms_and_nothing_else():
    """The project's forms that each beat the paper's alone (the LBS ones), on paper_full's losses and schedule."""
    lbs_forms = ("paper_full_softmax_weights", "paper_full_blended_centres")
    assert changed_keys("splatrig_deformer") == {k: v for form in lbs_forms for k, v in OUR_FORMS[form].items()}


def test_lpips_variant_is_the_papers_w_lp_not_a_table4_row():
    assert changed_keys("paper_full_lpips") == {
        "loss.terms.lpips.weight": (0.0, 0.2),
        "loss.terms.lpips.net": ("<absent>", "alex"),
    }
    header = _header("paper_full_lpips")
    assert "w/ L_p" in header and "Tables 2 and 3" in header and "Not a Table 4 row" in header
    assert "paper_full_lpips" not in _sweep_list("ablations")


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
    render = RenderOutput(
        rgb=torch.rand(1, h, w, 3, generator=g),
        alpha=torch.rand(1, h, w, 1, generator=g),
        depth=None,
        means2d=torch.zeros(1, 0, 2),
        radii=torch.zeros(1, 0),
    )
    return render, batch


def test_foreground_only_row_sees_nothing_outside_the_human_mask():
    """The paper's "only foreground" row: image loss (L1 and D-SSIM) on the human mask only, and no alpha loss, so
    whatever is rendered outside the mask (colour or opacity) costs nothing."""
    terms = composed("+experiment=foreground_only_loss")["loss"]["terms"]
    loss = CompositeLoss(terms)
    assert "alpha" not in loss.terms
    render, batch = _render_and_batch()
    inside = batch.mask[..., None].bool()
    agrees_inside = RenderOutput(
        rgb=torch.where(inside, batch.image, render.rgb),
        alpha=render.alpha,
        depth=None,
        means2d=render.means2d,
        radii=render.radii,
    )
    total, values = loss(agrees_inside, batch, {})
    assert total.item() == pytest.approx(0.0, abs=1e-6), values
    differs_inside = RenderOutput(
        rgb=torch.where(inside, 1 - batch.image, render.rgb),
        alpha=render.alpha,
        depth=None,
        means2d=render.means2d,
        radii=render.radii,
    )
    assert loss(differs_inside, batch, {})[0].item() > 1e-3
    assert changed_groups("foreground_only_loss") == {"loss"}


def test_boundary_row_removes_the_band_from_l1_and_alpha():
    """Changes confined to the band M_b = 0 (colour and opacity): paper_full's L1 and L_alpha do not see them; the
    "w/o boundary mask" row's L1 and L_alpha both do, and its alpha loss is eq. 7's over every pixel."""
    render, batch = _render_and_batch()
    band = batch.boundary[..., None] == 0  # [1, H, W, 1]
    mask = batch.mask[..., None]

    def with_band(rgb, alpha):
        return RenderOutput(
            rgb=torch.where(band, rgb, render.rgb),
            alpha=torch.where(band, alpha, render.alpha),
            depth=None,
            means2d=render.means2d,
            radii=render.radii,
        )

    exact, changed = with_band(batch.image, mask), with_band(1 - batch.image, 1 - mask)  # right / wrong in the band
    render = exact
    for row, sees_band in (("paper_full", False), ("no_boundary_mask", True)):
        loss = CompositeLoss(composed(f"+experiment={row}")["loss"]["terms"])
        before, after = loss(render, batch, {})[1], loss(changed, batch, {})[1]
        for term in ("l1", "alpha"):
            moved = abs(float(after[term]) - float(before[term]))
            assert (moved > 1e-3) is sees_band, (row, term, moved)
    terms = composed("+experiment=no_boundary_mask")["loss"]["terms"]
    alpha = CompositeLoss({"alpha": terms["alpha"]})(render, batch, {})[1]["alpha"]
    diff = render.alpha[..., 0] - batch.mask
    assert float(alpha) == pytest.approx(float(diff.square().mean()), rel=1e-6)


def test_simple_3dgs_lbs_drops_exactly_the_corrector_and_joint_optimisation():
    """The paper: "simple 3DGS+LBS" omits F_a and the joint optimisation; everything else is paper_full's."""
    assert changed_groups("simple_3dgs_lbs") == {"corrector", "pose_refine"}
    # the stripped-down variant keeps its own name and stays out of Table 4
    plain = composed("+experiment=plain_3dgs_lbs")
    assert plain["deformer"]["name"] == "lbs" and plain["stages"]["stage1_steps"] == 0
    assert "plain_3dgs_lbs" not in _sweep_list("ablations")


# ------------------------------------------------------------------------------------------------ the schedule
#: profile.schedule key -> the config keys paper_full derives from it
MILESTONES = {
    "stage1": ("stages.stage1_steps", "densifier.reset_restart"),
    "densify_start": ("densifier.refine_start",),
    "densify_stop": ("densifier.refine_stop",),
    "densify_every": ("densifier.refine_every",),
    "first_reset": ("densifier.first_reset",),
    "reset_every": ("densifier.reset_every",),
    "sh_every": ("gaussians.sh_increase_every",),
    "val_every": ("trainer.val_every",),
}
#: each profile's milestones at its own length (GPU: the paper's and 3DGS's steps; CPU: the steps it always had)
PROFILE_STEPS = {
    "gpu": (
        30000,
        {
            "stage1": 5000,
            "densify_start": 500,
            "densify_stop": 15000,
            "densify_every": 100,
            "first_reset": 3000,
            "reset_every": 6000,
            "sh_every": 1000,
            "val_every": 1000,
        },
    ),
    "cpu": (
        4000,
        {
            "stage1": 1000,
            "densify_start": 500,
            "densify_stop": 3000,
            "densify_every": 100,
            "first_reset": 400,
            "reset_every": 800,
            "sh_every": 1000,
            "val_every": 1000,
        },
    ),
}
PROFILE_STEPS["ablation"] = PROFILE_STEPS["cpu"]  # Table 4 runs at the CPU profile


def _milestones(*overrides: str) -> tuple[dict[str, int], dict]:
    cfg = composed("+experiment=paper_full", *overrides)
    values = flat(cfg)
    out = {}
    for name, keys in MILESTONES.items():
        (value,) = {values[k] for k in keys}  # keys derived from one fraction agree
        out[name] = value
    return out, cfg


@pytest.mark.parametrize("profile", sorted(PROFILE_STEPS))
def test_each_profile_declares_every_milestone_as_a_fraction(profile: str):
    steps_at, expected = PROFILE_STEPS[profile]
    got, cfg = _milestones(f"profile={profile}")
    assert cfg["trainer"]["max_steps"] == cfg["profile"]["max_steps"] == steps_at
    assert set(cfg["profile"]["schedule"]) == set(MILESTONES), "every milestone, and only those, in the schedule"
    assert got == expected


@pytest.mark.parametrize(("profile", "factor"), [("gpu", 0.5), ("gpu", 0.1), ("cpu", 2), ("cpu", 0.5)])
def test_max_steps_alone_moves_every_milestone_proportionally(profile: str, factor: float):
    """`profile.max_steps=N` is the one knob: at N = factor x the profile's length every milestone is factor x its
    step there (these lengths divide exactly), and every other key stays as it was."""
    steps_at, base = PROFILE_STEPS[profile]
    n = int(steps_at * factor)
    got, cfg = _milestones(f"profile={profile}", f"profile.max_steps={n}")
    assert cfg["trainer"]["max_steps"] == n
    assert got == {k: int(v * factor) for k, v in base.items()}
    a = flat(composed("+experiment=paper_full", f"profile={profile}"))
    b = flat(cfg)
    differ = {k for k in a if a[k] != b[k]}
    assert differ == {"trainer.max_steps", "profile.max_steps", *(k for keys in MILESTONES.values() for k in keys)}


@pytest.mark.parametrize("n", [1, 7, 333, 2000, 4001, 123457])
def test_milestones_are_rounded_fractions_of_any_length(n: int):
    got, cfg = _milestones("profile=cpu", f"profile.max_steps={n}")
    for name, value in got.items():
        fraction = cfg["profile"]["schedule"][name]
        assert value == max(1, int(float(fraction) * n + 0.5)), name


def test_steps_resolver():
    assert steps("5000/30000", 30000) == 5000 and steps("100/30000", 4000) == 13  # 13.33
    assert steps(0.125, 4) == 1 and steps(0.125, 12) == 2  # 0.5 and 1.5: halves round up
    assert steps(0.001, 100) == 1 and steps(0, 100) == 0  # a positive fraction never becomes step 0
    assert steps("1/3", 30) == 10 and steps(1, 4000) == 4000
    for bad in ("3/2", -0.1, "half"):
        with pytest.raises(ValueError, match="fraction"):
            steps(bad, 100)


def test_boundary_band_scales_with_the_image_side():
    """The paper's n = 5 at 512 px: n = max(1, round(5 * side / 512)); no band stays no band."""
    assert [scaled_half_width(5, side, 512) for side in (64, 96, 128, 256, 512, 1024)] == [1, 1, 1, 3, 5, 10]
    assert scaled_half_width(0, 512, 512) == 0 and scaled_half_width(5, 128, None) == 5


def _reset_steps(experiment: str, *overrides: str) -> tuple[list[int], dict]:
    """Opacity resets over a whole run of `experiment`, with the real stage-switch callback driving the densifier's
    schedule (as the trainer does, one call per training batch)."""
    from framework.lightning.callbacks import StageSwitch
    from framework.lightning.module import SplatModule

    cfg = composed(f"+experiment={experiment}", *overrides)
    densifier = build_component("densifier", cfg["densifier"])
    part = SimpleNamespace(enabled=False)
    module = SimpleNamespace(
        densifier=densifier,
        densifier_state=densifier.initialize_state(),
        avatar=SimpleNamespace(corrector=part, deformer=SimpleNamespace(enabled=False)),
        log=lambda *a, **k: None,
    )
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
        # 4000 steps: reset at 400, then every 800 after stage 2 starts at 1000, while densifying (until 3000)
        ("cpu", [400, 1800, 2600]),
        ("ablation", [400, 1800, 2600]),
    ],
)
def test_opacity_reset_schedule_of_each_profile(profile: str, expected: list[int]):
    resets, cfg = _reset_steps("paper_full", f"profile={profile}")
    assert resets == expected
    stage2 = int(cfg["stages"]["stage1_steps"])
    assert [s for s in resets if s < stage2] == [resets[0]], "one reset in stage 1"


@pytest.mark.parametrize("profile", ["gpu", "cpu"])
def test_no_first_stage_keeps_every_other_milestone(profile: str):
    """The row switches F_a and F_dw on from step 0 and moves nothing else: the same resets as paper_full (counted
    from where stage 2 would have started), the same densification window and SH steps."""
    full, _ = _reset_steps("paper_full", f"profile={profile}")
    row, cfg = _reset_steps("no_first_stage", f"profile={profile}")
    assert row == full and cfg["stages"]["stage1_steps"] == 0
    half, _ = _reset_steps(
        "no_first_stage", f"profile={profile}", f"profile.max_steps={PROFILE_STEPS[profile][0] // 2}"
    )
    assert half == [s // 2 for s in full]


def _tiny_module(experiment: str):
    from framework.lightning.module import SplatModule

    cfg = composed(
        f"+experiment={experiment}",
        "body=procedural",
        "deformer.grid_resolution=8",
        "gaussians.num=200",
        "rasterizer=torch_ref",
    )
    data_info = {
        "bounds": [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]],
        "num_frames_total": 2,
        "body_name": "procedural",
        "num_joints": 17,
    }
    return SplatModule(cfg, data_info)


def _batch(size: int = 16) -> FrameBatch:
    w2c = torch.tensor([[1.0, 0, 0, 0], [0, 0, -1, 0.0], [0, 1, 0, 3.0], [0, 0, 0, 1]])
    K = torch.tensor([[20.0, 0, size / 2], [0, 20.0, size / 2], [0, 0, 1]])
    z = torch.zeros(1, size, size)
    return FrameBatch(
        image=torch.zeros(1, size, size, 3),
        mask=z,
        boundary=z + 1,
        cameras=Cameras(K[None], w2c[None], size, size),
        frame=torch.zeros(1, dtype=torch.long),
        pose=torch.zeros(1, 17, 3),
        root=torch.eye(4)[None],
    )


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

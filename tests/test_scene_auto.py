"""`+scene=auto` (`framework.scene.auto`): each choice follows its measurement, each can be set by hand, and an
auto-chosen configuration trains; `python -m framework.prune` compacts what it trained."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from framework.errors import SplatrigError
from framework.scene.auto import apply_choices, choose, override_keys
from framework.scene.survey import SceneSurvey

THRESHOLDS = {
    "sh_view_dependence": [0.01, 0.02, 0.03],
    "corrector_pose_dependence": 0.008,
    "corrector_fold_pose_dependence": 0.015,
    "corrector_narrow_pose_dependence": 0.03,
    "corrector_narrow_hidden": 48,
    "weight_residual_skin_offset_px": 0.75,
    "gaussians_per_silhouette_px": 6.0,
    "min_gaussians": 1000,
    "max_gaussians_factor": 2.0,
}


def _survey(**changes) -> SceneSurvey:
    values = dict(
        key="k",
        dataset="d",
        body="procedural",
        width=128,
        height=128,
        views=9,
        frames=48,
        joints={"pelvis": 0.0, "spine": 12.0, "hand.L": 1.0, "head": 4.9},
        moving_deg=5.0,
        silhouette_px=1000.0,
        silhouette_fraction=0.06,
        silhouette_px_per_view={0: 1000.0},
        view_dependence=0.005,
        pose_dependence=0.0005,
        pose_noise=0.001,
        skin_offset_px=0.2,
    )
    values.update(changes)
    return SceneSurvey(**values)


def _by_key(choices):
    return {c.key: c.value for c in choices}


def test_choices_follow_the_survey_numbers():
    simple = _by_key(choose(_survey(), THRESHOLDS, root_joint="pelvis"))
    assert simple == {
        "scene.frozen_joints": ["hand.L", "head"],  # still (<= 5 deg) and not the root
        "gaussians.sh_degree": 0,
        "corrector": "none",
        "scene.fold_corrector": True,  # weak pose dependence: compaction may fold F_a
        "corrector.hidden": None,  # F_a is off: no width to choose
        "deformer": "lbs",
        "gaussians.num": 6000,  # 6 per silhouette pixel
        "densifier.max_gaussians": 12000,
    }
    demanding = _by_key(
        choose(
            _survey(view_dependence=0.025, pose_dependence=0.02, skin_offset_px=2.0, silhouette_px=100.0),
            THRESHOLDS,
            "pelvis",
        )
    )
    assert demanding["gaussians.sh_degree"] == 2 and demanding["corrector"] is None and demanding["deformer"] is None
    assert demanding["scene.fold_corrector"] is False  # 0.02 >= 0.015: F_a kept whole at compaction
    assert demanding["corrector.hidden"] == 48  # 0.02 < 0.03: a narrower F_a
    strong = _by_key(choose(_survey(pose_dependence=0.03), THRESHOLDS, "pelvis"))
    assert strong["corrector"] is None and strong["corrector.hidden"] is None  # at the threshold: width as configured
    older = {k: v for k, v in THRESHOLDS.items() if not k.startswith("corrector_narrow")}
    assert _by_key(choose(_survey(pose_dependence=0.02), older, "pelvis"))["corrector.hidden"] is None
    assert demanding["gaussians.num"] == 1000  # the floor
    assert _by_key(choose(_survey(view_dependence=0.5), THRESHOLDS, "pelvis"))["gaussians.sh_degree"] == 3


def _paper_full_auto(*extra: str):
    with initialize_config_module(config_module="framework.conf", version_base="1.3"):
        overrides = ["+experiment=paper_full", "+scene=auto", "profile=cpu", *extra]
        return compose(config_name="train", overrides=overrides)


def test_auto_composes_and_every_choice_can_be_overridden():
    cfg = _paper_full_auto()
    assert cfg.scene.auto and cfg.scene.survey and cfg.corrector.name == "latent"
    choices = choose(_survey(), dict(cfg.scene.thresholds), "pelvis")
    untouched = OmegaConf.to_container(cfg, resolve=False)
    # by hand: every key auto would set, in the forms people type them
    typed = [
        "scene.frozen_joints=[]",
        "gaussians.sh_degree=3",
        "corrector=latent",
        "scene.fold_corrector=false",
        "corrector.hidden=128",
        "deformer=lbs_residual",
        "profile.num_gaussians=8000",
        "densifier.max_gaussians=15000",
    ]
    done = apply_choices(cfg, choices, override_keys(typed))
    assert all(c.overridden and not c.applied for c in done)
    assert OmegaConf.to_container(cfg, resolve=False) == untouched
    # one at a time: only the key set by hand keeps its value, the others follow the survey
    for i, key in enumerate(typed):
        cfg = _paper_full_auto()
        done = apply_choices(cfg, choose(_survey(), dict(cfg.scene.thresholds), "pelvis"), override_keys([key]))
        assert [c.overridden for c in done] == [j == i for j in range(len(typed))]
    assert cfg.corrector.name == "none" and cfg.deformer.name == "lbs" and cfg.gaussians.sh_degree == 1  # the floor
    assert cfg.deformer.grid_resolution == 64 and "hidden" not in cfg.deformer  # the lbs option, residual keys gone
    # tuning a component's option is not choosing the component
    cfg = _paper_full_auto("deformer.grid_resolution=32")
    apply_choices(
        cfg, choose(_survey(), dict(cfg.scene.thresholds), "pelvis"), override_keys(["deformer.grid_resolution=32"])
    )
    assert cfg.deformer.name == "lbs" and cfg.deformer.grid_resolution == 32
    # F_a's width follows conf/scene/auto.yaml's threshold; an F_a set off by hand gets no width key
    walking = _survey(pose_dependence=0.02)
    cfg = _paper_full_auto()
    apply_choices(cfg, choose(walking, dict(cfg.scene.thresholds), "pelvis"), set())
    assert cfg.corrector.name == "latent" and cfg.corrector.hidden == cfg.scene.thresholds.corrector_narrow_hidden < 128
    cfg = _paper_full_auto("corrector=none")
    done = apply_choices(cfg, choose(walking, dict(cfg.scene.thresholds), "pelvis"), override_keys(["corrector=none"]))
    assert cfg.corrector.name == "none" and "hidden" not in cfg.corrector
    assert not next(c for c in done if c.key == "corrector.hidden").applied


TINY_AUTO = [
    "+experiment=paper_full",
    "+scene=auto",
    "trainer.fast_dev_run=true",
    "body=procedural",
    "data.body=procedural",
    "data.resolution=48",
    "data.num_views=6",
    "data.num_frames=8",
    "data.motion=arms",
    "data.supersample=1",
    "deformer.grid_resolution=12",
    "callbacks.progress_bar=false",
    "threads=1",
    "scene.max_frames=3",
]


@pytest.fixture(scope="module")
def auto_run(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """One fast_dev_run of paper_full + auto on an arms-only capture, with two of the choices set by hand."""
    tmp = tmp_path_factory.mktemp("auto")
    env = dict(os.environ, SPLATRIG_CACHE_DIR=str(tmp / "cache"), PYTHONUNBUFFERED="1")
    cmd = [
        sys.executable,
        "-m",
        "framework.train",
        *TINY_AUTO,
        "gaussians.sh_degree=2",
        "gaussians.num=321",
        f"paths.root={tmp / 'out'}",
    ]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900, cwd=tmp)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return next((tmp / "out" / "paper_full").glob("*")), proc


def test_auto_configuration_trains_under_fast_dev_run_and_keeps_hand_set_keys(auto_run):
    run, proc = auto_run
    cfg = yaml.safe_load((run / "config_resolved.yaml").read_text())
    joints = [
        "spine",
        "chest",
        "neck",
        "head",
        "hand.L",
        "hand.R",
        "upperleg.L",
        "lowerleg.L",
        "foot.L",
        "upperleg.R",
        "lowerleg.R",
        "foot.R",
    ]  # every joint but the root and the four arm joints
    assert cfg["scene"]["frozen_joints"] == joints
    assert cfg["deformer"]["name"] == "lbs" and cfg["deformer"]["grid_resolution"] == 12  # F_dw off, tuning kept
    assert cfg["gaussians"]["sh_degree"] == 2 and cfg["gaussians"]["num"] == 321  # set by hand, kept
    assert "gaussians.sh_degree: set by hand" in proc.stderr and "scene survey of" in proc.stderr
    scene = yaml.safe_load((run / "scene.yaml").read_text())
    assert {c["key"] for c in scene["choices"] if c["by_hand"]} == {"gaussians.sh_degree", "gaussians.num"}
    assert set(scene["frozen_pose"]) == set(joints)
    events = list((run / "tb").rglob("events.out.tfevents.*"))
    assert events and any(b"scene/choices" in e.read_bytes() for e in events)
    assert (run / "checkpoints" / "final.ckpt").is_file() and (run / "train_stats.json").is_file()


def test_prune_entry_point_writes_a_compact_model_that_loads(auto_run, tmp_path):
    run, _ = auto_run
    env = dict(os.environ, SPLATRIG_CACHE_DIR=str(run.parents[2] / "cache"), PYTHONUNBUFFERED="1")
    out = tmp_path / "compact.ckpt"
    cmd = [
        sys.executable,
        "-m",
        "framework.prune",
        f"ckpt={run / 'checkpoints' / 'final.ckpt'}",
        f"out={out}",
        "warmup=1",
        "repeats=2",
        f"json={tmp_path / 'report.json'}",
        "prune_tolerance=null",
        "refit_steps=0",
        "timing_rasterizer=numba",
    ]
    # the min_weight threshold alone (no faint-Gaussian pruning, no refit: the refit has its own test below)
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "novel-pose fps (numba)" in proc.stdout and "novel_pose PSNR dB" in proc.stdout and out.is_file()
    report = yaml.safe_load((tmp_path / "report.json").read_text())
    assert report["timing_rasterizer"] == "numba" and report["after"]["novel_pose_fps"] > 0
    before, after = report["before"], report["after"]
    assert after["num_gaussians"] == before["num_gaussians"] - report["removed_gaussians"]
    assert after["model_bytes"] <= before["model_bytes"] and after["sh_degree"] == 0  # one step: SH never switched on
    # deformer=lbs: the blend weights are the body's field at the means, so the compact model rebuilds them on loading
    # (the PSNR check below fails if they came back wrong)
    stored = torch.load(out, map_location="cpu", weights_only=False)["state_dict"]
    assert report["skin_weights_stored"] is False and "avatar.gaussians.params.skin_weights" not in stored
    # what pruning removed never reached 1/255 in a training view, so held-out renders barely move
    for split, value in before["psnr"].items():
        assert abs(after["psnr"][split] - value) < 0.05


def test_export_with_prune_writes_the_compact_model_and_exports_it(auto_run, tmp_path):
    run, _ = auto_run
    env = dict(os.environ, SPLATRIG_CACHE_DIR=str(run.parents[2] / "cache"), PYTHONUNBUFFERED="1")
    ckpt = run / "checkpoints" / "final.ckpt"
    cmd = [
        sys.executable,
        "-m",
        "framework.export",
        f"ckpt={ckpt}",
        "prune=true",
        f"out_dir={tmp_path / 'export'}",
        "refit_steps=10",
    ]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    compact = ckpt.with_name("final.pruned.ckpt")
    assert f"compact model: {compact}" in proc.stdout and "novel-pose fps" in proc.stdout
    ply = tmp_path / "export" / "canonical.ply"
    assert ply.is_file()
    from framework.formats.splat_ply import read_splat_ply

    pruned = torch.load(compact, map_location="cpu", weights_only=False)["state_dict"]
    assert read_splat_ply(ply).num == pruned["avatar.gaussians.params.means"].shape[0]  # the compact model's Gaussians


def test_refit_after_pruning_keeps_the_weights_rebuildable(auto_run, tmp_path, monkeypatch):
    """With `deformer=lbs` the blend weights are the body's field at the means; a refit moves the means, so the
    weights must follow them (as in training) for the compact model to rebuild them on loading rather than store them
    at the old means."""
    from framework.compaction.compact import prune_checkpoint, resolve_prune_tolerance

    run, _ = auto_run
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(run.parents[2] / "cache"))
    ckpt = run / "checkpoints" / "final.ckpt"
    # without a refit but at the tolerance the refit's "auto" means, so both keep the same Gaussians
    plain = prune_checkpoint(
        ckpt, tmp_path / "plain.ckpt", measure=False, device="cpu", refit_steps=0, prune_tolerance=0.03
    )
    refit = prune_checkpoint(ckpt, tmp_path / "refit.ckpt", measure=False, device="cpu", refit_steps=20)
    assert plain.refit is None and refit.refit["steps"] == 20 and refit.refit["stopped"] is None
    assert refit.prune_tolerance == 0.03 and resolve_prune_tolerance("auto", 0) == pytest.approx(0.7 / 255)
    a, b = (
        torch.load(tmp_path / f"{n}.ckpt", map_location="cpu", weights_only=False)["state_dict"]
        for n in ("plain", "refit")
    )
    key = "avatar.gaussians.params.means"
    assert a[key].shape == b[key].shape and not torch.equal(a[key], b[key])  # the same Gaussians, moved
    assert refit.skin_weights_stored is False and "avatar.gaussians.params.skin_weights" not in b
    assert "refit the remaining Gaussians for 20 steps" in refit.summary()


def test_a_second_pruning_round_prunes_the_refitted_model_again(auto_run, tmp_path, monkeypatch):
    """`prune_rounds=2`: the first round is the one-round compaction (deterministic), then the refitted model is
    pruned again within the same tolerance of its own renders and refitted again. So it keeps at most the one-round
    model's Gaussians, refits twice as long, and its counts add up to the Gaussians it ends with."""
    from framework.compaction.compact import prune_checkpoint

    run, _ = auto_run
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(run.parents[2] / "cache"))
    ckpt = run / "checkpoints" / "final.ckpt"
    kw = dict(measure=False, device="cpu", refit_steps=10, prune_tolerance=0.05)
    once = prune_checkpoint(ckpt, tmp_path / "once.ckpt", **kw)
    twice = prune_checkpoint(ckpt, tmp_path / "twice.ckpt", prune_rounds=2, **kw)
    assert once.refit["steps"] == 10 and twice.refit["steps"] == 20 and twice.refit["stopped"] is None
    assert twice.after.num_gaussians < once.after.num_gaussians < once.before.num_gaussians
    assert twice.before.num_gaussians - twice.removed_gaussians == twice.after.num_gaussians
    assert twice.removed_within_tolerance > once.removed_within_tolerance
    assert twice.skin_weights_stored is False  # the weights still follow the means through both refits
    assert "in 2 rounds of pruning and refit" in twice.summary() and "rounds of" not in once.summary()
    with pytest.raises(SplatrigError, match="prune_rounds=0"):
        prune_checkpoint(ckpt, tmp_path / "none.ckpt", prune_rounds=0, **kw)


def test_fold_tolerance_auto_keeps_the_corrector_whole_where_the_run_asked_for_it(
    tiny_avatar, tmp_path_factory, monkeypatch
):
    """`fold_tolerance=auto` reads the run's `scene.fold_corrector`: false (what `+scene=auto` writes for strongly
    pose-dependent appearance) keeps F_a exactly as trained; true (the default), or a tolerance given by hand, tries
    the fold."""
    from framework.compaction.compact import prune_checkpoint

    ckpt, cache = tiny_avatar  # paper_full: F_a with a random head
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(cache))
    tmp = tmp_path_factory.mktemp("fold_auto")
    source = torch.load(ckpt, map_location="cpu", weights_only=False)
    assert source["hyper_parameters"]["cfg"]["scene"]["fold_corrector"] is True  # train.yaml's default
    source["hyper_parameters"]["cfg"]["scene"]["fold_corrector"] = False
    keep = tmp / "keep.ckpt"
    torch.save(source, keep)
    options = dict(measure=False, device="cpu", refit_steps=0, prune_tolerance=None, min_weight=0.0)
    kept = prune_checkpoint(keep, tmp / "kept.pruned.ckpt", **options)
    assert kept.corrector_fold is None and "scene.fold_corrector is false" in kept.corrector_kept
    assert "F_a kept whole" in kept.summary()
    compact = torch.load(tmp / "kept.pruned.ckpt", map_location="cpu", weights_only=False)["state_dict"]
    corrector = [k for k in source["state_dict"] if k.startswith("avatar.corrector.")]
    assert corrector and "avatar.gaussians.params.latents" in compact
    for key in [*corrector, "avatar.gaussians.params.latents"]:  # the MLP and the latent codes, as trained
        assert torch.equal(compact[key], source["state_dict"][key]), key
    by_hand = prune_checkpoint(keep, tmp / "by_hand.ckpt", fold_tolerance=1.0, **options)
    assert by_hand.corrector_kept is None and by_hand.corrector_fold["folded"]  # 1.0 accepts any fold
    source["hyper_parameters"]["cfg"]["scene"]["fold_corrector"] = True
    torch.save(source, keep)
    tried = prune_checkpoint(keep, tmp / "tried.ckpt", **options)
    assert tried.corrector_kept is None and tried.corrector_fold["tolerance"] == pytest.approx(1 / 255)

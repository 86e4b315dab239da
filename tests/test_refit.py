"""The refit after pruning (`framework.compaction.refit`): it moves the Gaussians and nothing else, lowers the run's
own loss on the training frames, and gives back the parameters it started from when the loss turns non-finite."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest
import torch
import yaml
from trained_avatar import load_tiny

from framework.compaction.compact import DEFAULT_REFIT_STEPS, prune_checkpoint
from framework.compaction.pruning import prune_gaussians
from framework.compaction.refit import REFIT_KEYS, refit_gaussians
from framework.lightning.data import collate_frames


@pytest.fixture(scope="module")
def tiny(tiny_avatar):
    return tiny_avatar


@pytest.fixture
def pruned(tiny, monkeypatch):
    """The tiny avatar with every other Gaussian removed (a model the refit has something to repair in)."""
    ckpt, cache = tiny
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(cache))
    module, dm = load_tiny(ckpt)
    module.bake_weights()
    keep = torch.arange(module.avatar.gaussians.num) % 2 == 0
    prune_gaussians(module.avatar.gaussians, keep, module.avatar.corrector)
    return module, dm


def _training_loss(module, dm) -> float:
    """Mean of the run's own loss over every training frame, with gradients enabled as in training (the L_w term
    needs them) but none kept."""
    dataset = dm.train_set
    total = 0.0
    module.train()
    for i in range(len(dataset)):
        batch = collate_frames([dataset[i]])
        out = module.render_batch(batch)
        total += float(module.loss_fn(out.render, batch, out.aux)[0].detach())
    module.eval()
    return total / len(dataset)


def _state(module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def test_refit_moves_only_the_gaussians_and_lowers_the_training_loss(pruned) -> None:
    module, dm = pruned
    before_loss = _training_loss(module, dm)
    before = _state(module)
    result = refit_gaussians(module, dm, steps=60, progress=False)
    after = _state(module)
    assert result.steps == 60 and result.stopped is None
    moved = {k.split(".")[-1] for k in before if not torch.equal(before[k], after[k])}
    assert moved == set(REFIT_KEYS)  # every Gaussian parameter it optimises, and nothing else
    unchanged = [k for k in before if k.split(".")[-1] not in REFIT_KEYS]
    assert any("corrector" in k for k in unchanged) and any("pose_refiner" in k for k in unchanged)
    assert any(k.endswith("latents") for k in unchanged) and any(k.endswith("skin_weights") for k in unchanged)
    after_loss = _training_loss(module, dm)
    assert after_loss < 0.9 * before_loss, (before_loss, after_loss)
    assert not module.training


def test_refit_gives_back_its_start_when_the_loss_turns_non_finite(pruned, monkeypatch) -> None:
    module, dm = pruned
    before = _state(module)
    flags = {n: p.requires_grad for n, p in module.named_parameters()}
    calls = {"n": 0}
    forward = module.loss_fn.forward

    def failing(render, batch, aux):  # the run's loss, NaN on the fourth call
        calls["n"] += 1
        total, terms = forward(render, batch, aux)
        return (total * float("nan") if calls["n"] == 4 else total), terms

    monkeypatch.setattr(module.loss_fn, "forward", failing)
    result = refit_gaussians(module, dm, steps=10, progress=False)
    assert result.steps == 3 and "non-finite loss" in result.stopped and "step 3" in result.stopped
    after = _state(module)
    assert all(torch.equal(before[k], after[k]) for k in before)  # three updates were made, and undone
    assert {n: p.requires_grad for n, p in module.named_parameters()} == flags


def test_with_a_refit_the_partial_fold_gets_its_own_budget(tiny, tmp_path, monkeypatch) -> None:
    """Pruning to 0.03 RMS leaves the renders further from the originals than F_a's fold tolerance (1/255). Without a
    refit the partial fold is measured from the originals, so nothing can fold; with one it is measured from the
    pruned model (the refit repairs both steps), so part of a strongly pose-dependent F_a folds."""
    ckpt, cache = tiny
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(cache))
    stored = torch.load(ckpt, map_location="cpu", weights_only=False)
    stored["state_dict"]["avatar.corrector.head.weight"] *= 30.0  # corrections too varied to fold whole
    strong = tmp_path / "strong.ckpt"
    torch.save(stored, strong)
    folds = {}
    for steps in (0, 2):
        report = prune_checkpoint(
            strong,
            tmp_path / f"compact{steps}.ckpt",
            measure=False,
            device="cpu",
            prune_tolerance=0.03,
            refit_steps=steps,
        )
        assert report.render_rms > 0.02  # pruning went well past the fold tolerance
        folds[steps] = report.corrector_fold
    assert not folds[0]["folded"] and folds[0]["folded_gaussians"] == 0
    refit = folds[2]
    assert not refit["folded"] and 0 < refit["folded_gaussians"] < refit["num_gaussians"]
    assert refit["render_rms"] <= refit["tolerance"]


def test_the_command_lines_and_the_python_api_refit_as_long_by_default() -> None:
    """`framework.prune`, `framework.export prune=true` and `prune_checkpoint(...)` are three doors to one compaction:
    a default changed in one and not the others would make the same model compact differently by the door taken."""
    conf = Path(__file__).resolve().parents[1] / "conf"
    signature = inspect.signature(prune_checkpoint).parameters
    for name in ("prune.yaml", "export.yaml"):
        stored = yaml.safe_load((conf / name).read_text())
        assert stored["refit_steps"] == DEFAULT_REFIT_STEPS == signature["refit_steps"].default, name
        assert stored["prune_rounds"] == signature["prune_rounds"].default == 1, name
        assert stored["timing_rasterizer"] is None and signature["timing_rasterizer"].default is None, name

"""A deformer written against `framework.interfaces.Deformer` alone gets every engine feature a built-in one gets.

`OffsetSkinning` (below) is what a third party would write: LBS with the body's weight field plus a learned per-joint
offset as its stage-2 part, registered in the deformer registry as a plugin module registers itself, and removed
again after the test. It is trained through `framework.train.run` on tests/trained_avatar.py's tiny paper_full setup
(and that setup's rendered data), then compacted with `framework.compaction.compact.prune_checkpoint`.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
from torch import Tensor, nn

GRID = 12  # the weight field's resolution, small: the test is about the engine, not the field


@pytest.fixture
def offset_skinning() -> Iterator[type]:
    """The third-party deformer, registered as `offset_skinning` for the test's duration."""
    from framework.interfaces import Deformer, DeformOutput
    from framework.registry import DEFORMERS, register
    from framework.rig.lbs import lbs_with_sh_frames
    from framework.rig.sh_rotation import rotate_sh
    from framework.rig.weight_field import WeightField

    @register("deformer", "offset_skinning")
    class OffsetSkinning(Deformer):
        """LBS; weights: the body's weight field plus a per-joint offset that trains in stage 2."""

        seen: list[tuple[bool, Tensor]] = []  # (enabled, offset) at each training forward, for the test to read

        def __init__(self, grid_resolution: int = GRID, stretch: str = "diag", centres: str = "rigid") -> None:
            super().__init__()
            self.grid_resolution, self.stretch, self.centres = grid_resolution, stretch, centres
            self.offset: nn.Parameter | None = None

        def bind(self, body, bounds) -> None:
            self.field = WeightField.from_body(body, bounds, self.grid_resolution)
            self.offset = nn.Parameter(torch.zeros(body.num_joints))

        def weights(self, means: Tensor) -> Tensor:
            grid = self.field.sample(means)
            return grid + self.offset if self.enabled and self.offset is not None else grid

        def bake(self, gaussians):
            return self.weights(gaussians.means).detach()

        def release_after_bake(self) -> str:
            self.offset = None
            return "lbs"

        def forward(self, gaussians, bone_transforms, defer_sh=False):
            if self.training:  # what the stage switch left it with: on or off, and the offset's value
                self.seen.append((self.enabled, self.offset.detach().clone()))
            w = self.weights(gaussians.means) if gaussians.skin_weights is None else gaussians.skin_weights
            posed, R = lbs_with_sh_frames(gaussians, w, bone_transforms, self.stretch, torch.float32, self.centres)
            return DeformOutput(posed=posed.replace(sh=rotate_sh(posed.sh, R)), weights=w)

    try:
        yield OffsetSkinning
    finally:
        DEFORMERS.unregister("offset_skinning")


def _train(out: Path, steps: int) -> Path:
    """tests/trained_avatar.py's tiny paper_full run with `deformer=offset_skinning`, stage 2 from step 2, in this
    process; returns its checkpoints folder."""
    from hydra import compose, initialize_config_module
    from omegaconf import open_dict
    from trained_avatar import TRAIN

    from framework.train import run

    overrides = [o for o in TRAIN if not o.startswith(("deformer.", "trainer.max_steps", "stages."))]
    overrides += ["stages.stage1_steps=2", f"trainer.max_steps={steps}", f"paths.output_dir={out}"]
    with initialize_config_module(config_module="framework.conf", version_base="1.3"):
        cfg = compose(config_name="train", overrides=overrides)
    with open_dict(cfg):
        cfg.deformer = {"name": "offset_skinning", "grid_resolution": GRID, "stretch": "diag", "centres": "rigid"}
    run(cfg, overrides=overrides)
    return out / "checkpoints"


def _load(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)


@torch.no_grad()
def _renders(module, dm, items: int = 3) -> list[Tensor]:
    """The first `items` training images as the module renders them, [1, H, W, 3] each."""
    from framework.lightning.data import collate_frames

    module.eval()
    sh_degree = module.sh_degree(module.trained_steps())
    data = dm.train_set
    return [module.avatar(collate_frames([data[i]]), sh_degree=sh_degree).render.rgb for i in range(items)]


def test_a_third_party_deformer_gets_stage_switching_baking_and_compaction(
    offset_skinning: type, tiny_avatar: tuple[Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from framework.compaction.compact import prune_checkpoint
    from framework.lightning.trained_model import datamodule_for, load_module

    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(tiny_avatar[1]))  # the tiny avatar's rendered data
    key = "avatar.deformer.offset"

    # stage switching: in stage 1 the offset is off and stays at its zero initialisation; from step 2 it is on and
    # trains
    ckpts = _train(tmp_path / "run", steps=4)
    enabled = [on for on, _ in offset_skinning.seen]
    assert enabled[0] is False and enabled[-1] is True and enabled == sorted(enabled)  # off, then on for good
    assert all(not value.any() for on, value in offset_skinning.seen if not on)
    last = _load(ckpts / "last.ckpt")
    assert last["global_step"] == 4 and last["splatrig_stage"]["deformer_enabled"]
    offset = last["state_dict"][key]
    assert offset.abs().max() > 0

    # weight baking: final.ckpt stores each Gaussian's weights, the field's plus the trained offset
    final = _load(ckpts / "final.ckpt")
    means, baked = (final["state_dict"][f"avatar.gaussians.params.{k}"] for k in ("means", "skin_weights"))
    module = load_module(ckpts / "final.ckpt", "cpu")
    with torch.no_grad():  # the loaded deformer's field, the offset as stage 2 left it
        torch.testing.assert_close(baked, module.avatar.deformer.field.sample(means) + offset, atol=1e-6, rtol=0)

    # compaction: the offset leaves the checkpoint, which loads as plain `lbs` with the baked weights and renders the
    # training images as the trained model does (nothing pruned: min_weight 0, every SH band kept)
    out = tmp_path / "compact.ckpt"
    report = prune_checkpoint(
        ckpts / "final.ckpt",
        out,
        min_weight=0.0,
        sh_tolerance=0.0,
        measure=False,
        device="cpu",
        fold_tolerance=None,
        prune_tolerance=None,
        refit_steps=0,
    )
    compact = _load(out)
    assert report.weights_baked and compact["hyper_parameters"]["cfg"]["deformer"]["name"] == "lbs"
    assert key not in compact["state_dict"]
    torch.testing.assert_close(compact["state_dict"]["avatar.gaussians.params.skin_weights"], baked)
    dm = datamodule_for(module)
    reference = _renders(module, dm)
    for got, want in zip(_renders(load_module(out, "cpu"), dm), reference, strict=True):
        torch.testing.assert_close(got, want, atol=1e-4, rtol=0)

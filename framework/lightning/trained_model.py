"""A trained avatar and its data, rebuilt from a checkpoint: the one loader every entry point and tool uses.

`framework.evaluate`, `render`, `export`, `view`, `prune` and the benchmarks all start from a checkpoint file. They
share this module, so a checkpoint that loads for one loads for all, and a bad one fails with the same sentence
(`framework.lightning.checkpoint_io.read_checkpoint`).
"""

from __future__ import annotations

from pathlib import Path


def load_module(ckpt: str | Path, map_location: str = "cpu"):
    """The trained model of a checkpoint in eval mode, rebuilt from the config stored in it (errors name the file and
    the fix)."""
    from framework.lightning.checkpoint_io import CheckpointError, read_checkpoint
    from framework.lightning.module import SplatModule
    from framework.plugins import load_plugins

    checkpoint = read_checkpoint(ckpt, map_location)
    load_plugins()
    hparams = checkpoint["hyper_parameters"]
    module = SplatModule(hparams["cfg"], hparams["data_info"])
    module.on_load_checkpoint(checkpoint)  # resizes the Gaussians to the stored count, restores the stage
    try:
        module.load_state_dict(checkpoint["state_dict"])
    except RuntimeError as exc:
        lines = str(exc).strip().splitlines()
        detail = lines[min(1, len(lines) - 1)].strip()
        raise CheckpointError(
            f"ckpt={ckpt}: its tensors do not fit the model its own config builds ({detail}); it was written by an "
            f"incompatible version of splatrig or edited. Train it again."
        ) from None
    return module.to(map_location).eval()


def datamodule_for(module):
    """The splits of the dataset the module was trained on (rebuilt from its stored config)."""
    from framework.build import build_component
    from framework.lightning.data import FrameDataModule

    cfg = module.cfg

    def build_split(split: str):
        return build_component("dataset", cfg["data"], group="data", split=split)

    return FrameDataModule(build_split, val_split=cfg["eval"]["val_split"])

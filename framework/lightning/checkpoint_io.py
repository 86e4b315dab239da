"""Checkpoints that survive a kill: every save is atomic, and an unreadable checkpoint is named in one sentence.

Lightning's own writer serialises into a temporary file in the system temp folder and then *copies* it over the
target when that folder is on another file system (a kill during the copy leaves a truncated checkpoint), and never
syncs it to disk. `AtomicCheckpointIO` streams `torch.save` into a temporary file beside the target and renames it
over the target (`framework.atomic`), so `last.ckpt` is always the previous complete checkpoint or the new one.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.plugins.io import TorchCheckpointIO

from framework.atomic import atomic_path, remove_stale_temporaries
from framework.dataset_keys import upgrade_data_config
from framework.errors import SplatrigError
from framework.paths import checkpoint_file


class CheckpointError(SplatrigError):
    """A checkpoint file that cannot be used (missing, truncated, corrupted, or not a splatrig checkpoint)."""


def read_checkpoint(path: str | os.PathLike, map_location: Any = "cpu", what: str = "ckpt") -> dict[str, Any]:
    """torch.load of a splatrig checkpoint (`demo`: the shipped avatar); any failure is a CheckpointError naming the
    file and the fix. Every checkpoint is read here, so this is where an older one's stored dataset keys are
    translated to today's (`framework.dataset_keys.upgrade_data_config`)."""
    path = checkpoint_file(path)
    if not path.is_file():
        raise CheckpointError(
            f"{what}={path}: no such checkpoint file; point it at a run's checkpoints/last.ckpt (or final.ckpt)."
        )
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as exc:  # truncated zip, bad pickle, not a torch file at all
        reason = str(exc).split(". ")[0].strip().rstrip(".") or type(exc).__name__
        raise CheckpointError(
            f"{what}={path}: cannot be read as a checkpoint ({type(exc).__name__}: {reason}); the file is truncated "
            f"or corrupted. Use another checkpoint of the run (last.ckpt, final.ckpt) or train again."
        ) from None
    cfg = ckpt.get("hyper_parameters", {}).get("cfg") if isinstance(ckpt, dict) else None
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt or cfg is None:
        found = sorted(ckpt)[:8] if isinstance(ckpt, dict) else type(ckpt).__name__
        raise CheckpointError(
            f"{what}={path}: not a splatrig checkpoint (expected the keys state_dict and hyper_parameters.cfg "
            f"written by python -m framework.train, found {found})."
        )
    if isinstance(cfg.get("data"), Mapping):  # written before a dataset key was renamed: read under today's names
        cfg["data"] = upgrade_data_config(cfg["data"])
    return ckpt


class AtomicCheckpointIO(TorchCheckpointIO):
    """Atomic, durable saves (`framework.atomic`) and loads that fail with one clear message."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None) -> None:
        if storage_options is not None:
            raise TypeError(f"{type(self).__name__} does not take storage_options, got {storage_options!r}.")
        path = Path(path)
        remove_stale_temporaries(path)
        with atomic_path(path) as tmp:
            torch.save(checkpoint, tmp)

    def load_checkpoint(self, path: Any, map_location: Any | None = None, weights_only: bool | None = None):
        return read_checkpoint(path, map_location or "cpu")

"""Where generated assets and data live: one cache root, overridable for CI and clusters."""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path:
    """`$SPLATRIG_CACHE_DIR`, else `~/.cache/splatrig`; created on first use."""
    root = Path(os.environ.get("SPLATRIG_CACHE_DIR", Path.home() / ".cache" / "splatrig")).expanduser()
    root.mkdir(parents=True, exist_ok=True)
    return root


def data_dir() -> Path:
    """Generated datasets (the synthetic studio, static scenes)."""
    path = cache_dir() / "data"
    path.mkdir(parents=True, exist_ok=True)
    return path


DEMO = "demo"
"""`ckpt=demo`: the avatar shipped with the package (`framework/assets/demo_avatar.ckpt`), to look at untrained."""


def checkpoint_file(ckpt: str | Path) -> Path:
    """The file behind a `ckpt=` value: `demo` names the shipped avatar, anything else is a path."""
    if str(ckpt) == DEMO:
        return Path(__file__).resolve().parent / "assets" / "demo_avatar.ckpt"
    return Path(ckpt)


def beside_checkpoint(ckpt: str | Path, name: str) -> Path:
    """Default output folder of a command run on `ckpt` (a run's `<run>/checkpoints/<file>`): `<run>/<name>` for the
    run's own model, `final.ckpt` (where training writes its evaluation), `<run>/<name>_<stem>` for any other
    checkpoint (`eval_last`, `eval_final.pruned`), so evaluating, rendering or exporting a second checkpoint of a
    run never overwrites what the first one wrote. The shipped demo (`ckpt=demo`) writes to `outputs/demo/<name>`."""
    if str(ckpt) == DEMO:
        return Path("outputs") / DEMO / name
    path = Path(ckpt).resolve()
    run = path.parent.parent
    return run / name if path.name == "final.ckpt" else run / f"{name}_{path.stem}"

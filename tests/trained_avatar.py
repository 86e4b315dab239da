"""A tiny trained avatar for the viewer, export and motion-file tests (not a test module).

One short real training run of the paper's model on the procedural body (a few seconds), whose checkpoint is then
given random SH of degree 1, a random corrector head, a random weight-residual output layer and random pose/joint
residuals, so every path the tests compare (SH layout and rotation, corrections, F_dw, pose refinement) carries
non-trivial values. Built once per test run (the `tiny_avatar` fixture in tests/conftest.py) and shared through
`tiny_checkpoint`, whose file lock lets pytest-xdist's workers share one build.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import torch
from filelock import FileLock

TRAIN = [
    "+experiment=paper_full",
    "body=procedural",
    "data.body=procedural",
    "data.resolution=32",
    "data.num_views=4",
    "data.num_frames=6",
    "data.supersample=1",
    "deformer.grid_resolution=12",
    "gaussians.num=300",
    "gaussians.sh_increase_every=1",
    "stages.stage1_steps=2",
    "trainer.max_steps=4",
    "callbacks.progress_bar=false",
    "eval.after_fit=false",
    "logger=none",
    "threads=1",
]


def tiny_checkpoint(root: Path) -> tuple[Path, Path]:
    """(checkpoint path, SPLATRIG_CACHE_DIR it needs); trained under `root` by the first caller, in any process."""
    path, cache = root / "tiny.ckpt", root / "cache"
    with FileLock(str(root / "build.lock")):
        if not path.exists():
            _train_tiny(root, path, cache)
    return path, cache


def _train_tiny(root: Path, path: Path, cache: Path) -> None:
    """One real training run, then the random values above; `path` appears only when complete."""
    env = dict(os.environ, SPLATRIG_CACHE_DIR=str(cache), PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "framework.train", *TRAIN, f"paths.root={root / 'out'}"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=root)
    assert proc.returncode == 0, proc.stderr[-3000:]
    last = next((root / "out").rglob("last.ckpt"))
    ckpt = torch.load(last, map_location="cpu", weights_only=False)
    sd = ckpt["state_dict"]
    gen = torch.Generator().manual_seed(0)

    def rand(shape, scale: float) -> torch.Tensor:
        return scale * torch.randn(shape, generator=gen)

    shN = torch.zeros_like(sd["avatar.gaussians.params.shN"])
    shN[:, :3] = rand(shN[:, :3].shape, 0.4)  # degree 1 only: the package test rotates degree 1 itself
    sd["avatar.gaussians.params.shN"] = shN
    sd["avatar.corrector.head.weight"] = rand(sd["avatar.corrector.head.weight"].shape, 0.02)
    sd["avatar.corrector.head.bias"] = rand(sd["avatar.corrector.head.bias"].shape, 0.1)
    last_layer = max(
        (k for k in sd if k.startswith("avatar.deformer.mlp.") and k.endswith(".weight")),
        key=lambda k: int(k.split(".")[3]),
    )
    # small enough that w0 + F_dw (paper_full's additive form, not renormalised) stays a usable weight set
    sd[last_layer] = rand(sd[last_layer].shape, 0.05)
    sd["avatar.pose_refiner.pose_residual"] = rand(sd["avatar.pose_refiner.pose_residual"].shape, 0.05)
    sd["avatar.pose_refiner.joint_residual"] = rand(sd["avatar.pose_refiner.joint_residual"].shape, 0.005)
    partial = path.with_suffix(".partial")
    torch.save(ckpt, partial)
    partial.replace(path)


def load_tiny(ckpt: Path):
    """(module in eval mode, its datamodule), loaded in this process (SPLATRIG_CACHE_DIR must point at the cache)."""
    from framework.lightning.trained_model import datamodule_for, load_module

    module = load_module(ckpt)
    module.eval()
    return module, datamodule_for(module)

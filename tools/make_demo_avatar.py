"""The avatar shipped as `ckpt=demo` (`framework/assets/demo_avatar.ckpt`): a compact model without its body buffers.

    python -m framework.train +experiment=paper_full seed=0                       # the CPU profile, embedded studio
    python -m framework.prune ckpt=<run>/checkpoints/final.ckpt prune_tolerance=0.04
    python tools/make_demo_avatar.py <run>/checkpoints/final.pruned.ckpt         # writes the package's demo

The compacted checkpoint already holds no optimizer state; this drops the body model's buffers too (vertices, faces,
skin weights: rebuilt from the body config when the demo loads, `framework.lightning.trained_model.with_body_buffers`)
and checks the file stays under the package's 3 MiB budget.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from framework.atomic import atomic_path
from framework.lightning.checkpoint_io import read_checkpoint
from framework.lightning.trained_model import BODY_PREFIX
from framework.paths import DEMO, checkpoint_file

MAX_BYTES = 3 * 2**20


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ckpt", help="a compacted checkpoint (python -m framework.prune)")
    ap.add_argument("--out", type=Path, default=checkpoint_file(DEMO))
    a = ap.parse_args(argv)
    ckpt = read_checkpoint(a.ckpt)
    ckpt["state_dict"] = {k: v for k, v in ckpt["state_dict"].items() if not k.startswith(BODY_PREFIX)}
    ckpt.pop("optimizer_states", None)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(a.out) as tmp:
        torch.save(ckpt, tmp)
    size = a.out.stat().st_size
    print(f"{a.out}: {size / 2**20:.2f} MiB, {ckpt['state_dict']['avatar.gaussians.params.means'].shape[0]} Gaussians")
    if size > MAX_BYTES:
        print(f"error: {a.out} is over the {MAX_BYTES / 2**20:.0f} MiB budget; prune further (prune_tolerance)")
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Real-time rendering of a trained (or synthetic) avatar: frames per second per rasterizer backend.

    python tools/bench_render.py --ckpt outputs/paper_full/<run>/checkpoints/final.ckpt
    python tools/bench_render.py --num 20000 --body anny --resolution 512 --device cuda --json fps.json

Two cases, as a viewer uses them:
- novel view: one pose seen from a new camera; the corrected, posed Gaussians are cached, so only rasterisation runs.
- novel pose: a new pose every frame: F_a correction + LBS (baked weights) + rasterisation.
Timing covers the whole frame (synchronised on CUDA); medians of `--repeats` frames after `--warmup`.
Without --ckpt, Gaussians are sampled on the body surface and the paper's latent corrector is used as initialised.
"""

from __future__ import annotations

import argparse
import json

import torch

from framework.cameras import orbit_cameras
from framework.model.avatar import Avatar, GaussianParams
from framework.model.frame_timing import time_frames
from framework.plugins import format_table, load_plugins
from framework.registry import BODIES, CORRECTORS, DEFORMERS, RASTERIZERS
from framework.types import FrameBatch


def synthetic_avatar(body_name: str, num: int, device: str) -> Avatar:
    from framework.model.gaussian_init import from_body_surface

    body = BODIES.build(body_name)
    g = from_body_surface(body, num=num, sh_degree=3, seed=0, opacity=0.8)
    corrector = CORRECTORS.build("latent")
    corrector.bind(body.num_pose_features)
    deformer = DEFORMERS.build("lbs", grid_resolution=32)
    lo, hi = body.rest_vertices.min(0).values, body.rest_vertices.max(0).values
    deformer.bind(body, torch.stack([lo - 0.1, hi + 0.1]))
    g.skin_weights = deformer.bake(g).detach()  # the real-time path uses baked weights
    return Avatar(GaussianParams(g), RASTERIZERS.build("torch_ref"), corrector, deformer, body).to(device)


def trained_avatar(ckpt: str, device: str) -> Avatar:
    from framework.evaluate import load_module

    module = load_module(ckpt, map_location=device)
    module.bake_weights()
    return module.avatar.to(device)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ckpt", default=None)
    ap.add_argument("--body", default="anny")
    ap.add_argument("--num", type=int, default=20000, help="Gaussians (synthetic avatar only)")
    ap.add_argument("--resolution", type=int, default=512)
    ap.add_argument("--backends", nargs="*", default=None, help="default: every available rasterizer")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    load_plugins()
    avatar = trained_avatar(args.ckpt, args.device) if args.ckpt else synthetic_avatar(args.body, args.num, args.device)
    avatar.eval()
    body = avatar.body
    J = body.num_input_joints
    center = (body.rest_vertices.min(0).values + body.rest_vertices.max(0).values) / 2
    cams = orbit_cameras(center.cpu(), 3.0, 0.0, 16, args.resolution, args.resolution, fov_deg=40).to(args.device)
    gen = torch.Generator().manual_seed(0)
    poses = (0.25 * torch.randn(64, J, 3, generator=gen)).to(args.device)
    res = args.resolution
    names = args.backends or [e.name for e in RASTERIZERS if e.unavailable_reason() is None]
    rows, records = [], []
    for name in names:
        reason = RASTERIZERS.entry(name).unavailable_reason()
        if reason:
            rows.append((name, "-", "-", reason))
            continue
        avatar.rasterizer = RASTERIZERS.build(name)

        def frame(i: int, novel_pose: bool) -> None:
            pose = poses[i % len(poses) if novel_pose else 0][None]
            dev = args.device
            batch = FrameBatch(
                image=torch.empty(1, res, res, 3, device=dev), mask=torch.empty(1, res, res, device=dev),
                boundary=torch.empty(1, res, res, device=dev), cameras=cams.index(i % cams.num),
                frame=torch.zeros(1, dtype=torch.long, device=dev), pose=pose,
            )  # fmt: skip
            avatar(batch, sh_degree=3)

        with torch.no_grad():
            t_view = time_frames(lambda i: frame(i, False), args.warmup, args.repeats, args.device)
            t_pose = time_frames(lambda i: frame(i, True), args.warmup, args.repeats, args.device)
        rows.append((name, f"{1 / t_view:.1f}", f"{1 / t_pose:.1f}", ""))
        records.append({"backend": name, "novel_view_fps": 1 / t_view, "novel_pose_fps": 1 / t_pose})
    n = avatar.gaussians.num
    print(f"\n{n} Gaussians, {res}x{res}, device {args.device}, {J} joints; medians of {args.repeats} frames\n")
    print(format_table(rows, ("backend", "novel-view fps", "novel-pose fps", "note")))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"num_gaussians": n, "resolution": res, "device": args.device, "results": records}, f, indent=2)


if __name__ == "__main__":
    main()

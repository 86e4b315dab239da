"""Real-time rendering of a trained (or synthetic) avatar: frames per second per rasterizer backend.

    python tools/bench_render.py --ckpt outputs/paper_full/<run>/checkpoints/final.ckpt
    python tools/bench_render.py --num 20000 --body anny --resolution 512 --device cuda --json fps.json

Two cases, as a viewer uses them:
- novel view: one pose seen from a new camera; the corrected, posed Gaussians are cached, so only rasterisation runs.
- novel pose: a new pose every frame: F_a correction + LBS (baked weights) + rasterisation.
Timing covers the whole frame (synchronised on CUDA); medians of `--repeats` frames after `--warmup`.

A second table splits the novel-pose frame of the first backend into its parts (bone transforms, F_a, LBS, the view
colour, the rasterizer), timed in a further pass of frames with the clock read after each part; each part's median
is over those frames, so the parts add up to about, not exactly, the novel-pose frame of the first table,
and a last line bounds the novel-pose / novel-view ratio from below on this machine: the novel-view frame plus F_a's
forward FLOPs (counted by torch's FlopCounterMode) at the best sgemm rate measured in the same run
(`_bench.gemm_rate`), with nothing charged for the rest of the pose path.

The parts table also counts, in one frame, the operators each part issues, those of them that queue device work (a
kernel or a copy; the others are views and bare allocations) and the host waits among them (`_bench.host_waits`):
what a GPU's host pays per frame whatever the device computes. `--accelerator-path` builds the avatar with the torch
execution (`execution.kernels=torch`: a GPU's torch code on a CPU, no compiled kernels), so those counts are a GPU's
on any machine.

`--scaling` times the same parts on random subsets of the avatar's Gaussians (all, 1/2, 1/4, 1/50; a partially folded
corrector keeps its rows among them) and fits each part as fixed + per-Gaussian cost (least squares). The fixed part
is what a frame costs however small the model: it bounds how much faster a pruned model can render (a model with
fewer Gaussians saves only the per-Gaussian part).

Without --ckpt, Gaussians are sampled on the body surface and the paper's latent corrector is used as initialised.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable

import torch
from _bench.gemm_rate import gemm_rate
from _bench.host_waits import OperatorCount, cuda_device_events

from framework.cameras import orbit_cameras
from framework.evaluation.frame_timing import synchronize, time_frames
from framework.execution import COMPILED, Execution
from framework.model.avatar import Avatar, GaussianParams
from framework.plugins import format_table, load_plugins
from framework.registry import BODIES, CORRECTORS, DEFORMERS, RASTERIZERS
from framework.runtime import default_device
from framework.splat.sh import sh_degree_of_bases
from framework.types import Cameras, FrameBatch, RenderOutput

SYNTHETIC_SH_DEGREE = 3


def synthetic_avatar(body_name: str, num: int, device: str, execution: Execution = COMPILED) -> Avatar:
    from framework.model.gaussian_init import from_body_surface

    body = BODIES.build(body_name)
    g = from_body_surface(body, num=num, sh_degree=SYNTHETIC_SH_DEGREE, seed=0, opacity=0.8)
    corrector = CORRECTORS.build("latent")
    corrector.bind(body.num_pose_features)
    deformer = DEFORMERS.build("lbs", grid_resolution=32)
    deformer.set_execution(execution)  # before the bake: its weights are the ones this execution computes
    lo, hi = body.rest_vertices.min(0).values, body.rest_vertices.max(0).values
    deformer.bind(body, torch.stack([lo - 0.1, hi + 0.1]))
    g.skin_weights = deformer.bake(g).detach()  # the real-time path uses baked weights
    rasterizer = RASTERIZERS.build("torch_ref")
    return Avatar(GaussianParams(g), rasterizer, corrector, deformer, body, execution=execution).to(device)


def trained_avatar(ckpt: str, device: str, kernels: str | None = None) -> tuple[Avatar, int]:
    """The checkpoint's avatar with baked weights, and the SH degree its stored coefficients hold: a compact model from
    `framework.export prune=true` may keep fewer bands than paper_full's 3; a short run's bands that its schedule had
    not switched on yet are zero and are timed all the same, as a full run's would be."""
    from framework.lightning.trained_model import load_module

    module = load_module(ckpt, map_location=device, kernels=kernels)
    module.bake_weights()
    return module.avatar.to(device), sh_degree_of_bases(module.avatar.gaussians.gaussians().sh.shape[1])


def frame_batch(cams: Cameras, pose: torch.Tensor, i: int, res: int, device: str) -> FrameBatch:
    """The batch of frame i: camera i of the orbit, `pose` [1, J, 3]; image tensors are placeholders (not read)."""
    return FrameBatch(
        image=torch.empty(1, res, res, 3, device=device),
        mask=torch.empty(1, res, res, device=device),
        boundary=torch.empty(1, res, res, device=device),
        cameras=cams.index(i % cams.num),
        frame=torch.zeros(1, dtype=torch.long, device=device),
        pose=pose,
    )


def orbit_and_poses(avatar: Avatar, res: int, device: str) -> tuple[Cameras, torch.Tensor]:
    """The timed frames' cameras (16 on an orbit around the body, `res` x `res`) and poses (64 random ones,
    [64, J, 3], the same for every model: seed 0)."""
    body = avatar.body
    center = (body.rest_vertices.min(0).values + body.rest_vertices.max(0).values) / 2
    cams = orbit_cameras(center.cpu(), 3.0, 0.0, 16, res, res, fov_deg=40).to(device)
    gen = torch.Generator().manual_seed(0)
    poses = (0.25 * torch.randn(64, body.num_input_joints, 3, generator=gen)).to(device)
    return cams, poses


def view_and_pose_seconds(
    avatar: Avatar, sh_degree: int, cams: Cameras, poses: torch.Tensor, device: str, warmup: int, repeats: int
) -> tuple[float, float]:
    """(novel-view, novel-pose) median seconds of a whole frame with the avatar's rasterizer: novel view renders the
    first pose from the orbit's cameras in turn (the posed Gaussians cached), novel pose a new pose every frame."""
    res = cams.width

    def frame(i: int, novel_pose: bool) -> None:
        pose = poses[i % len(poses) if novel_pose else 0][None]
        avatar(frame_batch(cams, pose, i, res, device), sh_degree=sh_degree)

    with torch.no_grad():
        t_view = time_frames(lambda i: frame(i, False), warmup, repeats, device)
        t_pose = time_frames(lambda i: frame(i, True), warmup, repeats, device)
    return t_view, t_pose


POSE_PARTS = ("bone transforms", "corrector F_a", "LBS (polar, skinning)", "view colour (SH at R^T d)", "rasterizer")


def pose_frame(
    avatar: Avatar, batch: FrameBatch, sh_degree: int, mark: Callable[[], None] = lambda: None
) -> RenderOutput:
    """`Avatar.forward`'s novel-pose path for one camera, written out part by part; `mark` is called after each of
    the `POSE_PARTS` (tests check that the image equals the avatar's own)."""
    transforms, pose_features = avatar.bone_transforms(batch)
    mark()
    corrected = avatar.corrector(avatar.gaussians.gaussians(sh_degree), pose_features)
    mark()
    deformed = avatar.deformer(corrected, transforms, defer_sh=True)
    mark()
    posed, sh, degree = deformed.posed, deformed.posed.sh, sh_degree
    if deformed.sh_frames is not None:
        sh, degree = avatar._view_colour(posed, deformed.sh_frames, batch, sh_degree), 0
    mark()
    out = avatar.rasterizer.render(
        posed.means,
        posed.quats,
        torch.exp(posed.log_scales),
        torch.sigmoid(posed.opacity_logits),
        sh,
        batch.cameras,
        sh_degree=degree,
        background=avatar.background,
    )
    mark()
    return out


def pose_frame_parts(
    avatar: Avatar, batches: list[FrameBatch], sh_degree: int, warmup: int, device: str
) -> dict[str, float]:
    """Median ms of each part of the novel-pose frame over `batches` (one new pose each) after `warmup` of them."""
    times: dict[str, list[float]] = {k: [] for k in POSE_PARTS}
    with torch.no_grad():
        for i, batch in enumerate(batches):
            marks = [time.perf_counter()]

            def mark(marks: list[float] = marks) -> None:
                synchronize(device)
                marks.append(time.perf_counter())

            pose_frame(avatar, batch, sh_degree, mark)
            if i >= warmup:
                for k, a, b in zip(POSE_PARTS, marks[:-1], marks[1:], strict=True):
                    times[k].append((b - a) * 1e3)
    return {k: statistics.median(v) for k, v in times.items()}


def pose_frame_operators(avatar: Avatar, batch: FrameBatch, sh_degree: int) -> dict[str, tuple[int, int, int]]:
    """(operators issued, those queuing device work, host waits) of each part of one novel-pose frame
    (`_bench.host_waits`): on a GPU each operator costs the host a dispatch, each of the second kind a kernel
    launch or a copy too, and each wait drains the device's queue."""
    counter = OperatorCount()
    marks: list[tuple[int, int, int]] = []

    def mark() -> None:
        marks.append((counter.operators, counter.launches, counter.waits))

    with torch.no_grad(), counter:
        mark()
        pose_frame(avatar, batch, sh_degree, mark)
    return {
        k: tuple(after - before for before, after in zip(a, b, strict=True))
        for k, a, b in zip(POSE_PARTS, marks[:-1], marks[1:], strict=True)
    }


def corrector_gflop(avatar: Avatar, pose_features: torch.Tensor) -> float:
    """GFLOP of one F_a forward over the avatar's Gaussians (0 without an MLP corrector). Counted with gradients
    on, so that F_a takes its plain layers: the counter does not see oneDNN's fused ones (`corrector_mlp`)."""
    from torch.utils.flop_counter import FlopCounterMode

    counter = FlopCounterMode(display=False)
    with torch.enable_grad(), counter:
        avatar.corrector(avatar.gaussians.gaussians(3), pose_features)
    return counter.get_total_flops() / 1e9


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ckpt", default=None)
    ap.add_argument("--body", default="anny")
    ap.add_argument("--num", type=int, default=20000, help="Gaussians (synthetic avatar only)")
    ap.add_argument("--resolution", type=int, default=512)
    ap.add_argument("--backends", nargs="*", default=None, help="default: every available rasterizer")
    ap.add_argument("--device", default=default_device())
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--json", default=None)
    ap.add_argument("--scaling", action="store_true", help="fit each part as fixed + per-Gaussian cost")
    ap.add_argument(
        "--accelerator-path",
        action="store_true",
        help="run a GPU's torch code on this CPU (the torch execution, no compiled kernels): its operators and host "
        "waits, and at a small size the host's cost of a frame",
    )
    args = ap.parse_args()
    kernels = "torch" if args.accelerator_path else "auto"
    load_plugins()
    if args.ckpt:
        avatar, degree = trained_avatar(args.ckpt, args.device, kernels)
    else:
        execution = Execution.resolve(kernels, args.device)
        avatar, degree = synthetic_avatar(args.body, args.num, args.device, execution), SYNTHETIC_SH_DEGREE
    avatar.eval()
    J = avatar.body.num_input_joints
    cams, poses = orbit_and_poses(avatar, args.resolution, args.device)
    res = args.resolution
    names = args.backends or [e.name for e in RASTERIZERS if e.unavailable_reason() is None]
    rows, records = [], []
    view_ms: dict[str, float] = {}
    for name in names:
        reason = RASTERIZERS.entry(name).unavailable_reason()
        if reason:
            rows.append((name, "-", "-", reason))
            continue
        avatar.rasterizer = RASTERIZERS.build(name)
        t_view, t_pose = view_and_pose_seconds(avatar, degree, cams, poses, args.device, args.warmup, args.repeats)
        view_ms[name] = t_view * 1e3
        rows.append((name, f"{1 / t_view:.1f}", f"{1 / t_pose:.1f}", ""))
        records.append({"backend": name, "novel_view_fps": 1 / t_view, "novel_pose_fps": 1 / t_pose})
    n = avatar.gaussians.num
    where = f"{res}x{res}, device {args.device}, {J} joints"
    print(f"\n{n} Gaussians, SH degree {degree}, {where}; medians of {args.repeats} frames\n")
    print(format_table(rows, ("backend", "novel-view fps", "novel-pose fps", "note")))
    report: dict = {"num_gaussians": n, "sh_degree": degree, "resolution": res, "device": args.device}
    report["results"] = records
    if view_ms:
        report["pose_path"] = pose_path_report(avatar, degree, view_ms, cams, poses, args)
        if args.scaling:
            report["scaling"] = scaling_report(avatar, degree, next(iter(view_ms)), cams, poses, args)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=2)


def pose_path_report(
    avatar: Avatar,
    sh_degree: int,
    view_ms: dict[str, float],
    cams: Cameras,
    poses: torch.Tensor,
    args: argparse.Namespace,
) -> dict:
    """Print (and return) the novel-pose frame's parts for the first timed backend and the ratio's lower bound."""
    name = next(iter(view_ms))
    avatar.rasterizer = RASTERIZERS.build(name)
    res, dev = args.resolution, args.device
    batches = [frame_batch(cams, poses[i % len(poses)][None], i, res, dev) for i in range(args.warmup + args.repeats)]
    parts = pose_frame_parts(avatar, batches, sh_degree, args.warmup, dev)
    counts = pose_frame_operators(avatar, batches[-1], sh_degree)
    pose_only = sum(v for k, v in parts.items() if k != "rasterizer")
    pose_ops = [sum(c[i] for k, c in counts.items() if k != "rasterizer") for i in (0, 1, 2)]
    view = view_ms[name]
    print(
        f"\nNovel-pose frame of {name}, part by part (medians of {args.repeats} frames, ms; operators issued, those "
        f"queuing device work and host waits of one frame, _bench.host_waits):\n"
    )
    table = [(k, f"{v:.1f}", f"{v / view:.2f}x", *counts[k]) for k, v in parts.items()]
    table.append(("pose path (all but the rasterizer)", f"{pose_only:.1f}", f"{pose_only / view:.2f}x", *pose_ops))
    header = ("part", "ms", "of the novel-view frame", "operators", "queue device work", "host waits")
    print(format_table(table, header))
    with torch.no_grad():
        device_events = cuda_device_events(lambda: pose_frame(avatar, batches[-1], sh_degree, lambda: None))
    if device_events is not None:
        print(
            f"\nKernels, copies and fills the GPU ran for one novel-pose frame, rasterizer included "
            f"(torch.profiler): {device_events}"
        )
    with torch.no_grad():
        _, pose_features = avatar.bone_transforms(batches[0])
    gflop = corrector_gflop(avatar, pose_features) if pose_features is not None else 0.0
    rate = max(gemm_rate(max(3, args.repeats // 2), dev))
    floor_ms = gflop / rate * 1e3
    bound = (view + floor_ms) / view
    print(
        f"\nLower bound on this machine: the novel-view frame ({view:.1f} ms) plus F_a's {gflop:.3f} GFLOP forward at "
        f"the best sgemm rate of this run ({rate:.0f} GFLOP/s: {floor_ms:.1f} ms), nothing else of the pose path: "
        f"novel-pose / novel-view >= {bound:.2f}x (the parts measure {(view + pose_only) / view:.2f}x)."
    )
    return {
        "backend": name,
        "parts_ms": parts,
        "parts_operators_launches_waits": counts,
        "novel_view_ms": view,
        "cuda_device_events_per_frame": device_events,
        "corrector_gflop": gflop,
        "best_sgemm_gflops": rate,
        "corrector_floor_ms": floor_ms,
        "ratio_lower_bound": bound,
    }


SCALING_FRACTIONS = (1.0, 0.5, 0.25, 0.02)


def subset_avatar(avatar: Avatar, count: int, seed: int = 0) -> Avatar:
    """A copy of `avatar` with `count` of its Gaussians, drawn at random (so the subset covers the body as the whole
    model does); a partially folded corrector keeps its rows among them
    (`framework.compaction.pruning.prune_gaussians`)."""
    import copy

    from framework.compaction.pruning import prune_gaussians

    sub = copy.deepcopy(avatar)
    n = sub.gaussians.num
    order = torch.randperm(n, generator=torch.Generator().manual_seed(seed))
    keep = torch.zeros(n, dtype=torch.bool)
    keep[order[: max(1, min(count, n))]] = True
    rows = getattr(sub.corrector, "active_rows", None)
    if rows is not None and rows.numel() and not bool(keep.to(rows.device)[rows].any()):
        keep[rows[0].cpu()] = True  # at least one corrected row stays, or the corrector would have nothing to run on
    prune_gaussians(sub.gaussians, keep.to(sub.gaussians.params["means"].device), sub.corrector)
    sub._posed_cache = None
    return sub


def fit_fixed_and_slope(counts: list[int], ms: list[float]) -> tuple[float, float]:
    """Least-squares line ms = fixed + slope * count -> (fixed ms, ms per Gaussian)."""
    n = len(counts)
    mean_c, mean_t = sum(counts) / n, sum(ms) / n
    var = sum((c - mean_c) ** 2 for c in counts)
    slope = sum((c - mean_c) * (t - mean_t) for c, t in zip(counts, ms, strict=True)) / var if var else 0.0
    return mean_t - slope * mean_c, slope


def scaling_report(
    avatar: Avatar, sh_degree: int, name: str, cams: Cameras, poses: torch.Tensor, args: argparse.Namespace
) -> dict:
    """Print (and return) each part of the novel-pose frame as fixed + per-Gaussian cost, from subsets of the model."""
    res, dev = args.resolution, args.device
    batches = [frame_batch(cams, poses[i % len(poses)][None], i, res, dev) for i in range(args.warmup + args.repeats)]
    n = avatar.gaussians.num
    counts = sorted({max(2, round(f * n)) for f in SCALING_FRACTIONS}, reverse=True)
    subsets = {c: subset_avatar(avatar, c) for c in counts}  # copies carry the rasterizer `name` set above
    rounds = 3  # interleaved: a drifting machine speed moves every subset alike
    samples: dict[int, list[dict[str, float]]] = {c: [] for c in counts}
    for _ in range(rounds):
        for c in counts:
            samples[c].append(pose_frame_parts(subsets[c], batches, sh_degree, args.warmup, dev))
    parts = {c: {k: statistics.median(s[k] for s in samples[c]) for k in POSE_PARTS} for c in counts}
    rows, fits = [], {}
    for k in (*POSE_PARTS, "whole frame"):
        ms = [sum(parts[c].values()) if k == "whole frame" else parts[c][k] for c in counts]
        fixed, slope = fit_fixed_and_slope(counts, ms)
        fits[k] = {"fixed_ms": fixed, "ms_per_1000": slope * 1e3, "ms": dict(zip(counts, ms, strict=True))}
        rows.append((k, *(f"{t:.2f}" for t in ms), f"{fixed:.2f}", f"{slope * 1e3:.3f}"))
    print(
        f"\nNovel-pose frame of {name} on random subsets of the {n} Gaussians (medians of {rounds} interleaved rounds "
        f"of {args.repeats} frames, ms), fitted as fixed + per-Gaussian cost:\n"
    )
    print(format_table(rows, ("part", *(f"N={c}" for c in counts), "fixed ms", "ms per 1000 Gaussians")))
    whole = fits["whole frame"]
    full_ms = whole["ms"][counts[0]]
    half_ms = full_ms - 0.5 * counts[0] * whole["ms_per_1000"] / 1e3  # the same frame with half the Gaussians
    print(
        f"\nFixed cost: {whole['fixed_ms']:.1f} of {full_ms:.1f} ms at N={counts[0]}; a model with half the Gaussians "
        f"renders about {full_ms / half_ms:.2f}x faster on this machine, all else equal."
    )
    return {"backend": name, "counts": counts, "fits": fits}


if __name__ == "__main__":
    main()

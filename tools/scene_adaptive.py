"""paper_full against `+scene=auto` (+ pruning) on three studio scenes that need different things; writes the table.

    python tools/scene_adaptive.py --out outputs/scene_adaptive                 # the comparison (hardware profile)
    python tools/scene_adaptive.py --out /tmp/scene_smoke --smoke               # the same commands, 50 steps

Scenes (synthetic studio, `framework/data/studio.py`):
- near_static: `data.motion=idle`, a slight nod and arm sway in matte (Lambertian) cloth;
- walking: the default capture (walk, arm raises, squats, kicks; matte cloth with pose-dependent folds);
- demanding: `data.look=glossy +data.garment=skirt`, the default motion in cloth with a view-dependent highlight and
  deep pose-dependent folds, plus a loose skirt that follows the pelvis with lag and swing (not the body's skinning).
Per scene: two trainings (`+experiment=paper_full` and `+experiment=paper_full +scene=auto`, subprocesses, run folders
`<out>/<scene>/<variant>`), then in this process, one after the other: the paper_full model measured, the auto model
pruned (`framework.compaction.compact.prune_checkpoint`, which measures before and after). Speed follows
tools/bench_render.py's rules; training time is the fit loop's wall time and peak memory the training process's peak
RSS (CUDA: peak allocated), both from the run's `train_stats.json`. A finished training is not repeated (delete its
folder to redo it), so an interrupted comparison resumes. Extra `--set key=value` overrides go to every training.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

# as framework.train: this process measures between trainings, and spinning OpenMP threads would take CPU from them
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import yaml  # noqa: E402

SCENES: dict[str, list[str]] = {
    "near_static": ["data.motion=idle"],
    "walking": [],
    "demanding": ["data.look=glossy", "+data.garment=skirt"],
}
VARIANTS: dict[str, list[str]] = {"paper_full": [], "auto": ["+scene=auto"]}
#: the smoke run: the full commands at 50 steps, no evaluation inside training (the table measures PSNR itself)
SMOKE = [
    "profile.max_steps=50",
    "profile.schedule.stage1=0.4",
    "profile.schedule.densify_start=0.2",
    "profile.schedule.densify_stop=0.8",
    "profile.schedule.densify_every=0.2",
    "profile.schedule.sh_every=1",
    "profile.schedule.val_every=1",
    "callbacks.image_every=1000",
    "callbacks.checkpoint_every=1000",
    "eval.after_fit=false",
    "deformer.grid_resolution=32",
]
SMOKE_REFIT_STEPS = 20  # and a refit as short: the default 1500 steps would be most of the smoke run's time


def train(run_dir: Path, overrides: list[str]) -> dict:
    """Train into `run_dir` unless it already holds a finished run; returns its train_stats.json."""
    stats, final = run_dir / "train_stats.json", run_dir / "checkpoints" / "final.ckpt"
    if stats.is_file() and final.is_file():
        print(f"[scene_adaptive] reusing {run_dir}", flush=True)
        return json.loads(stats.read_text())
    run_dir.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "framework.train", "+experiment=paper_full", *overrides, f"hydra.run.dir={run_dir}"]
    print(f"[scene_adaptive] {' '.join(cmd[2:])}", flush=True)
    t0 = time.perf_counter()
    with open(run_dir / "train.log", "w") as log:
        proc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    if proc.returncode != 0 or not final.is_file():
        sys.exit(f"[scene_adaptive] training failed ({proc.returncode}); see {run_dir / 'train.log'}")
    print(f"[scene_adaptive]   done in {time.perf_counter() - t0:.0f} s", flush=True)
    return json.loads(stats.read_text())


def measure_scene(
    scene_dir: Path,
    warmup: int,
    repeats: int,
    rounds: int,
    prune_options: dict | None = None,
    rasterizer: str | None = None,
) -> dict:
    """paper_full measured and auto pruned (sizes and PSNR before and after; `prune_options` go to
    `prune_checkpoint`, whose defaults `python -m framework.prune` uses), then the three models' frame rates,
    interleaved over `rounds` rounds (medians), rendered with `rasterizer` (default: the one they trained with)."""
    from framework.compaction.compact import measure_module, prune_checkpoint
    from framework.lightning.trained_model import datamodule_for, interleaved_fps, load_module

    full_ckpt = scene_dir / "paper_full" / "checkpoints" / "final.ckpt"
    module = load_module(full_ckpt, map_location=_device())
    dm = datamodule_for(module)
    full = measure_module(module, dm, repeats=0, file_bytes=full_ckpt.stat().st_size)  # fps: interleaved below
    auto_ckpt = scene_dir / "auto" / "checkpoints" / "final.ckpt"
    pruned_ckpt = auto_ckpt.with_name("final.pruned.ckpt")
    report = prune_checkpoint(auto_ckpt, pruned_ckpt, repeats=0, device=_device(), **(prune_options or {}))
    measures = {"paper_full": full.__dict__, "auto": report.before.__dict__, "auto+pruned": report.after.__dict__}
    fps = interleaved_fps(
        {"paper_full": full_ckpt, "auto": auto_ckpt, "auto+pruned": pruned_ckpt},
        warmup,
        repeats,
        rounds,
        _device(),
        rasterizer,
    )
    for name, (pose_fps, view_fps) in fps.items():
        measures[name].update(novel_pose_fps=pose_fps, novel_view_fps=view_fps)
    return {
        **measures,
        "removed_gaussians": report.removed_gaussians,
        "corrector_fold": report.corrector_fold,
        "compaction": {
            "removed_within_tolerance": report.removed_within_tolerance,
            "prune_tolerance": report.prune_tolerance,
            "render_rms": report.render_rms,
            "skin_weights_stored": report.skin_weights_stored,
            "refit": report.refit,
            "corrector_kept": report.corrector_kept,
        },
    }


def _device() -> str:
    from framework.runtime import default_device

    return default_device()


def scene_table(name: str, result: dict) -> str:
    from framework.compaction.compact import skin_weights_outcome
    from framework.plugins import format_table

    rows = []
    base = result["measures"]["paper_full"]
    for variant in ("paper_full", "auto", "auto+pruned"):
        m = result["measures"][variant]
        stats = result["train"]["auto" if variant == "auto+pruned" else variant]
        peak = stats.get("cuda_peak_mib") or stats.get("peak_rss_mib")
        refit = (result.get("compaction") or {}).get("refit") if variant == "auto+pruned" else None
        seconds = stats["fit_seconds"] + (refit["seconds"] if refit else 0.0)  # the refit is training too
        psnr = m["psnr"]
        rows.append(
            (
                variant,
                str(m["num_gaussians"]),
                str(m["sh_degree"]),
                f"{m['model_bytes'] / 2**20:.2f}",
                f"{m['novel_pose_fps']:.1f} ({m['novel_pose_fps'] / base['novel_pose_fps']:.2f}x)",
                f"{seconds:.0f}",
                f"{peak:.0f}",
                f"{psnr.get('novel_view', float('nan')):.2f}",
                f"{psnr.get('novel_pose', float('nan')):.2f}",
                f"{base['model_bytes'] / m['model_bytes']:.2f}x",
            )
        )
    header = (
        "variant",
        "Gaussians",
        "SH",
        "model MiB",
        "novel-pose fps",
        "train s",
        "peak MiB",
        "novel-view dB",
        "novel-pose dB",
        "smaller",
    )
    choices = "; ".join(
        f"{c['key']}={_short(c['value'])} ({c['measure']})" for c in result["choices"] if not c["by_hand"]
    )
    fold, comp = result.get("corrector_fold"), result.get("compaction") or {}
    pruned = f"pruning removed {result['removed_gaussians']} Gaussians"
    if comp.get("prune_tolerance") is not None:
        within = comp["prune_tolerance"]
        pruned += f" ({comp['removed_within_tolerance']} of them the least needed, within {within:.4f})"
    if fold:
        from framework.compaction.corrector_fold import fold_outcome

        pruned += (
            f"; F_a {fold_outcome(fold)}: training frames render {fold['render_rms']:.4f} RMS apart, "
            f"tolerance {fold['tolerance']:.4f}"
        )
    if comp.get("corrector_kept"):
        pruned += f"; F_a kept whole: {comp['corrector_kept']}"
    if comp.get("render_rms") is not None:
        pruned += (
            f"; the compact model renders the checked training frames {comp['render_rms']:.4f} RMS from "
            f"the trained one; {skin_weights_outcome(comp['skin_weights_stored'])}"
        )
    if comp.get("refit"):
        r = comp["refit"]
        pruned += (
            f"; then the remaining Gaussians refitted for {r['steps']} steps ({r['seconds']:.0f} s, in the "
            f"train s of auto+pruned)"
        )

    return f"### {name}\n\nauto chose: {choices}\n\n{pruned}\n\n{format_table(rows, header)}\n"


def _short(value) -> str:
    if isinstance(value, list):
        return f"[{len(value)} joints]"
    return "keep" if value is None else str(value)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("outputs/scene_adaptive"))
    ap.add_argument("--scenes", nargs="*", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--profile", default=None, help="hardware profile for every training (default: chosen by GPU)")
    ap.add_argument("--smoke", action="store_true", help=f"50-step trainings: {' '.join(SMOKE)}")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="extra overrides for every training")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--rounds", type=int, default=15, help="interleaved rounds of frame-rate timing (medians)")
    ap.add_argument("--prune-tolerance", type=float, default=None, help="default: framework.prune's (auto)")
    ap.add_argument("--refit-steps", type=int, default=None, help="default: framework.prune's")
    ap.add_argument(
        "--rasterizer",
        default=None,
        help="time the frames with this backend (e.g. numba); default: the one the models trained with",
    )
    args = ap.parse_args()
    prune_options = {
        k: v for k, v in (("prune_tolerance", args.prune_tolerance), ("refit_steps", args.refit_steps)) if v is not None
    }
    if args.smoke:
        prune_options.setdefault("refit_steps", SMOKE_REFIT_STEPS)
    extra = ([f"profile={args.profile}"] if args.profile else []) + (SMOKE if args.smoke else []) + list(args.set)
    results = {}
    for scene in args.scenes:
        scene_dir = args.out / scene
        train_stats = {v: train(scene_dir / v, [*SCENES[scene], *o, *extra]) for v, o in VARIANTS.items()}
        summary = yaml.safe_load((scene_dir / "auto" / "scene.yaml").read_text())
        measures = measure_scene(scene_dir, args.warmup, args.repeats, args.rounds, prune_options, args.rasterizer)
        results[scene] = {
            "train": train_stats,
            "measures": measures,
            "choices": summary["choices"],
            "profile": summary["profile"],
        }
        results[scene]["removed_gaussians"] = results[scene]["measures"].pop("removed_gaussians")
        results[scene]["corrector_fold"] = results[scene]["measures"].pop("corrector_fold")
        results[scene]["compaction"] = results[scene]["measures"].pop("compaction")
        tmp = args.out / "results.json.tmp"
        tmp.write_text(json.dumps(results, indent=1))
        os.replace(tmp, args.out / "results.json")
    device = _device()
    lines = [
        f"# scene-adaptive comparison{' (SMOKE RUN: 50 steps, numbers are not results)' if args.smoke else ''}",
        "",
        f"device {device}; overrides for every training: `{' '.join(extra) or '(none)'}`; pruning: "
        f"`{prune_options or 'framework.prune defaults'}`",
        "",
    ]
    lines += [scene_table(scene, results[scene]) for scene in args.scenes]
    (args.out / "scene_adaptive.md").write_text("\n".join(lines))
    print("\n".join(lines))
    print(f"[scene_adaptive] written: {args.out / 'scene_adaptive.md'}, {args.out / 'results.json'}")


if __name__ == "__main__":
    main()

"""Record the viewer's frame rate of every finished run under the given sweep folders in its results.json
(`viewer_fps`), at one square resolution, on two paths: the compiled CPU kernels with the numba rasterizer, and the
torch execution with torch_ref (a GPU's torch code on this device).

    python tools/record_fps.py outputs/tradeoff/<part 1> [outputs/tradeoff/<part 2> ...] [--resolution 512]

Why: the `render_fps` a run records at the end of training is timed at the data's resolution with the rasterizer the
run trained with, so points that train smaller or with another backend are not timed alike. Here every model renders
the same frames (tools/bench_render.py's orbit cameras and random poses, its timing rules) at the viewer's size.
Runs that already hold the field are skipped, so an interrupted call continues where it stopped.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from bench_render import orbit_and_poses, trained_avatar, view_and_pose_seconds

FIELD = "viewer_fps"
PATHS = {"compiled": ("auto", "numba"), "torch": ("torch", "torch_ref")}  # path -> (kernels, rasterizer)


def run_checkpoint(run: Path, record: dict[str, Any]) -> Path | None:
    """The run's model: results.json's `checkpoint` (a file name in checkpoints/) when it exists, else
    checkpoints/final.ckpt when that exists, else None."""
    named = record.get("checkpoint")
    if named:
        path = run / "checkpoints" / str(named)
        if path.is_file():
            return path
    final = run / "checkpoints" / "final.ckpt"
    return final if final.is_file() else None


def pending(folders: list[Path]) -> list[tuple[Path, Path]]:
    """(run folder, checkpoint) of each run below `folders` with a results.json and a checkpoint, no `viewer_fps`."""
    runs = []
    for folder in folders:
        for path in sorted(Path(folder).rglob("results.json")):
            record = json.loads(path.read_text())
            ckpt = run_checkpoint(path.parent, record)
            if FIELD not in record and ckpt is not None:
                runs.append((path.parent, ckpt))
    return runs


def path_fps(ckpt: Path, kernels: str, rasterizer: str, res: int, device: str, warmup: int, repeats: int) -> dict:
    """{"novel_pose", "novel_view"} fps of the checkpoint's avatar loaded with `kernels`, rendered with `rasterizer`,
    plus "num_gaussians" and "sh_degree"; fps None (and "unavailable": why) when the rasterizer cannot run here."""
    from framework.registry import RASTERIZERS

    avatar, degree = trained_avatar(str(ckpt), device, kernels)
    out: dict[str, Any] = {"num_gaussians": int(avatar.gaussians.num), "sh_degree": int(degree)}
    reason = RASTERIZERS.entry(rasterizer).unavailable_reason()
    if reason is not None:
        return {**out, "novel_pose": None, "novel_view": None, "unavailable": reason}
    avatar.rasterizer = RASTERIZERS.build(rasterizer)
    avatar.eval()
    cams, poses = orbit_and_poses(avatar, res, device)
    t_view, t_pose = view_and_pose_seconds(avatar, degree, cams, poses, device, warmup, repeats)
    return {**out, "novel_pose": round(1 / t_pose, 2), "novel_view": round(1 / t_view, 2)}


def viewer_fps(ckpt: Path, res: int, device: str, warmup: int, repeats: int) -> dict[str, Any]:
    """The `viewer_fps` field of one checkpoint (schema: framework.evaluation.run_record)."""
    paths, model = {}, {}
    for name, (kernels, rasterizer) in PATHS.items():
        measured = path_fps(ckpt, kernels, rasterizer, res, device, warmup, repeats)
        model = {"num_gaussians": measured.pop("num_gaussians"), "sh_degree": measured.pop("sh_degree")}
        paths[name] = measured
    return {"resolution": res, "device": device, "warmup": warmup, "frames": repeats, **model, "paths": paths}


def _fps(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", type=Path, help="sweep folders (searched for results.json)")
    ap.add_argument("--resolution", type=int, default=512, help="square frame side, pixels")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=10, help="frames timed (medians)")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args(argv)
    from framework.evaluation.run_record import record_field
    from framework.plugins import load_plugins

    load_plugins()
    runs = pending(args.folders)
    print(f"{len(runs)} runs to time at {args.resolution}x{args.resolution} on {args.device}", flush=True)
    for i, (run, ckpt) in enumerate(runs, 1):
        try:
            value = viewer_fps(ckpt, args.resolution, args.device, args.warmup, args.repeats)
        except Exception as exc:  # one unreadable model must not stop the others; a later call retries it
            print(f"[{i}/{len(runs)}] {run.name}: failed: {type(exc).__name__}: {exc}", flush=True)
            continue
        record_field(run, FIELD, value)
        cells = "  ".join(
            f"{name}: pose {_fps(p['novel_pose'])} view {_fps(p['novel_view'])} fps"
            for name, p in value["paths"].items()
        )
        print(f"[{i}/{len(runs)}] {run.name} ({value['num_gaussians']} Gaussians): {cells}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

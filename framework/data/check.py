"""`python -m framework.data.check data=easymocap data.root=PATH [body=smplx body.model_path=FILE]`: run this before
training on your own capture. It projects the posed body into every camera's masks and says which cameras or frames
disagree, and why (framework.data.calibration_check has the method and the mistakes it recognises).

The body: the capture's stored posed vertices when it has them (EasyMocap's `--write_vertices`, ZJU's vertices/),
otherwise the configured `body` posed by the stored parameters (with the data's fitted shape). Frames: `frames`
evenly spaced training frames (all of them with frames=null). Prints a table per camera and the problems found, and
writes report.md, report.json and one overlay_<index>_<camera>.png per camera (its worst sampled frame: mask tinted
blue with a yellow outline, projected silhouette outlined in magenta, vertices as green / red dots) to `out_dir`.
Exit status: 0 when every camera agrees, 1 when problems were found, 2 for unusable input.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig

from framework.atomic import atomic_write_text
from framework.cli import hydra_main
from framework.errors import SplatrigError, reported_as_message


def sample_frames(frames: list[int], count: int | None) -> list[int]:
    """`count` frames evenly spread over `frames` (first and last included); all of them for None."""
    if count is None or count >= len(frames):
        return list(frames)
    idx = np.unique(np.round(np.linspace(0, len(frames) - 1, max(int(count), 1))).astype(int))
    return [frames[i] for i in idx]


def _body_geometry(ds: Any, body: Any):
    """frame -> Geometry, and a description of where the body comes from."""
    import torch

    from framework.data.calibration_check import Geometry

    if ds.has_vertices():
        faces = None
        if body is not None:
            faces = body.faces.cpu().numpy()
            if len(ds.vertices(ds.train_frame_ids[0])) != int(body.rest_vertices.shape[0]):
                faces = None
        what = "stored posed vertices" + (" with the body's triangles" if faces is not None else " (point splats)")
        return (lambda f: Geometry(ds.vertices(f).double().numpy(), faces)), what
    if body is None:
        raise SplatrigError(
            f"{ds.root}: the capture stores no posed vertices, so the check poses a body model with its parameters; "
            f"pass the body they were fitted with, e.g. body=smpl body.model_path=/path/to/SMPL_NEUTRAL.pkl (or "
            f"body=smplx)"
        )
    poses, roots = ds.poses(), ds.roots()
    faces = body.faces.cpu().numpy()

    def geometry(f: int) -> Geometry:
        with torch.no_grad():
            local = body.posed_vertices(poses[f : f + 1].to(body.rest_vertices.dtype))[0].double()
        world = local @ roots[f, :3, :3].double().T + roots[f, :3, 3].double()
        return Geometry(world.numpy(), faces)

    return geometry, f"body '{body.registry_name}' posed by the parameters"


def _write_text(path: Path, text: str) -> None:
    atomic_write_text(path, text)


def run(cfg: DictConfig) -> int:
    from omegaconf import OmegaConf
    from omegaconf.errors import MissingMandatoryValue
    from tqdm import tqdm

    from framework.build import build_component, build_split, with_fitted_betas
    from framework.data.calibration_check import Rig, diagnose, project, score
    from framework.data.overlay import render_tile, write_png
    from framework.data.sequence_dataset import SequenceDataset
    from framework.plugins import load_plugins

    load_plugins()
    try:
        data = OmegaConf.to_container(cfg.data, resolve=True, throw_on_missing=True)
        body_node = OmegaConf.to_container(cfg.body, resolve=True, throw_on_missing=True)
    except MissingMandatoryValue as exc:
        raise SplatrigError(f"{exc.full_key} is not set: pass {exc.full_key}=/path/to/your/capture") from None
    ds = build_split(data, "train")
    if not isinstance(ds, SequenceDataset):
        raise SplatrigError(
            f"data={data['name']}: the check reads calibrated captures (easymocap, zju_mocap, "
            f"synthetic_studio); '{data['name']}' is not one"
        )
    body = None
    if body_node.get("name"):
        betas = ds.fitted_betas().tolist()
        body = build_component("body", with_fitted_betas(body_node, betas))
    geometry_of, what = _body_geometry(ds, body)
    cache: dict[int, Any] = {}

    def geometry(f: int):
        if f not in cache:
            cache[f] = geometry_of(f)
        return cache[f]

    masks: dict[tuple[int, int], np.ndarray] = {}

    def mask(c: int, f: int) -> np.ndarray:
        if (c, f) not in masks:
            masks[c, f] = ds.load_uint8(f, c)[1] >= 128
        return masks[c, f]

    frames = sample_frames(ds.train_frame_ids, cfg.frames)
    stems = getattr(ds.seq, "stems", None)

    def frame_name(f: int) -> str:
        return stems[f] if stems is not None else str(f)

    rig = Rig(
        ds.cameras.K.double().numpy(),
        ds.cameras.world_to_cam.double().numpy(),
        list(ds.seq.camera_names),
        ds.height,
        ds.width,
    )
    C = len(rig.names)
    source = getattr(ds, "mask_source", None) or ds.mask_dir
    print(
        f"[splatrig] check {ds.root}: {len(frames)} frame(s) x {C} camera(s) at {ds.width}x{ds.height}, masks from "
        f"{source}, body from {what}",
        file=sys.stderr,
    )
    scores: dict[tuple[int, int], tuple[float, float]] = {}
    for f, c in tqdm([(f, c) for f in frames for c in range(C)], desc="check", unit="image"):
        inside, iou, _ = score(geometry(f), mask(c, f), rig.K[c], rig.w2c[c])
        scores[c, f] = (inside, iou)
    report = diagnose(rig, frames, geometry, mask, scores, float(cfg.min_inside), float(cfg.min_iou), frame_name)

    out = Path(str(cfg.out_dir)).expanduser()
    out.mkdir(parents=True, exist_ok=True)
    for r in tqdm(report.rows, desc="overlays", unit="camera", leave=False):
        f, c = r.worst_frame, r.index
        img, m = ds.load_uint8(f, c)
        g = geometry(f)
        uv, z = project(g.points, rig.K[c], rig.w2c[c])
        _, iou, sil = score(g, m >= 128, rig.K[c], rig.w2c[c])
        label = f"camera {r.name} frame {frame_name(f)} IoU {iou:.2f}"
        tile, _ = render_tile(img / 255.0, m / 255.0, uv[z > 0], label, crop=False, side=512, silhouette=sil)
        write_png(out / f"overlay_{c:02d}_{r.name}.png", tile)
    table = report.markdown(frame_name)
    _write_text(out / "report.md", f"# Capture check: {ds.root}\n\nBody from {what}; masks from {source}.\n\n{table}\n")
    summary = {
        "root": str(ds.root),
        "ok": report.ok,
        "cameras": [vars(r) for r in report.rows],
        "findings": report.findings,
        "frames": [frame_name(f) for f in frames],
    }
    _write_text(out / "report.json", json.dumps(summary, indent=1))
    print(table)
    print(f"\n[splatrig] report and one overlay per camera: {out}")
    return 0 if report.ok else 1


@hydra_main("check")
def _hydra_main(cfg: DictConfig) -> None:
    with reported_as_message():
        code = run(cfg)
    sys.exit(code)


def main() -> None:
    _hydra_main()


if __name__ == "__main__":
    main()

"""`python -m framework.data.convert root=CAPTURE out=FOLDER`: an EasyMocap capture in the ZJU-MoCap layout, for tools
that expect annots.npy / params/ / vertices/ (Neural Body, Animatable NeRF, our `data=zju_mocap`).

What it writes (framework.data.zju.layout.ZjuWriter): images copied byte for byte under <OUT>/<camera name>/
(renumbered 000000.. in the order of the selected frames), binary masks under mask/, annots.npy with K and D as
stored, R, and T in millimetres, params/{i}.npy with the poses as the reader gives them (SMPL-X hand PCA expanded to
165 values) plus "body", vertices/{i}.npy when EasyMocap wrote vertices, and easymocap_source.json saying where each
frame came from. `data=zju_mocap data.protocol=null data.root=OUT` then reads the same samples as
`data=easymocap data.root=ROOT` (tests/test_easymocap.py checks it).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np

from framework.atomic import atomic_write_text
from framework.data.easymocap_layout import EasyMocapSequence
from framework.data.sequence_dataset import frame_range
from framework.data.zju.layout import ANNOTS
from framework.data.zju.writer import ZjuWriter
from framework.errors import SplatrigError, reported_as_message


def easymocap_to_zju(
    root: str | os.PathLike,
    out: str | os.PathLike,
    *,
    cameras: list[str] | None = None,
    frames: list[int] | None = None,
    mask_dir: str = "auto",
    params_dir: str = "auto",
    person_id: int | None = None,
    smplx_model_path: str | None = None,
    gender: str = "neutral",
    force: bool = False,
    progress: bool = True,
) -> Path:
    """Convert; `frames` is a frame_range spec over the capture's frames ([start, end, step] or a list)."""
    from tqdm import tqdm

    seq = EasyMocapSequence(
        root,
        cameras=cameras,
        mask_dir=mask_dir,
        params_dir=params_dir,
        person_id=person_id,
        smplx_model_path=smplx_model_path,
        smplx_gender=gender,
    )
    out = Path(out)
    if (out / ANNOTS).exists() and not force:
        raise SplatrigError(f"{out / ANNOTS} exists: {out} already holds a sequence; pick another out= or force=true")
    selected = frame_range(frames, seq.num_frames, "frames")
    exts = {seq.image_path(f, v).suffix.lower() for f in selected[:1] for v in range(seq.num_views)}
    if len(exts) != 1:
        raise SplatrigError(
            f"{seq.root}: cameras store frames in different formats {sorted(exts)}; convert them to one format first"
        )
    writer = ZjuWriter(out, seq.camera_names, image_ext=exts.pop())
    cams = seq.cameras
    writer.write_cameras(cams.K, cams.D, cams.R, cams.T_m, k_convention="opencv")
    for i, f in enumerate(tqdm(selected, desc="convert", unit="frame", disable=not progress)):
        masks = np.stack([seq.mask(f, v) for v in range(seq.num_views)])
        vertices = seq.vertices(f) if seq.vertices_dir is not None else None
        writer.copy_frame(i, [seq.image_path(f, v) for v in range(seq.num_views)], masks, seq.params(f), vertices)
    source = {
        "source": str(seq.root.resolve()),
        "cameras": seq.camera_names,
        "mask_dir": seq.mask_dir,
        "params_dir": str(seq.params_dir.relative_to(seq.root)),
        "frames": [seq.stems[f] for f in selected],  # frame i of OUT is the capture's frame stem frames[i]
    }
    atomic_write_text(out / "easymocap_source.json", json.dumps(source, indent=1))
    return writer.finish(len(selected)).parent


def main() -> int:
    from omegaconf import DictConfig, OmegaConf

    from framework.cli import hydra_main

    @hydra_main("convert")
    def _main(cfg: DictConfig) -> None:
        with reported_as_message():
            if cfg.source != "easymocap":
                raise SplatrigError(f"source={cfg.source}: no converter for it; the one source is easymocap")
            out = easymocap_to_zju(
                cfg.root,
                cfg.out,
                cameras=None if cfg.cameras is None else [str(c) for c in cfg.cameras],
                frames=OmegaConf.to_container(cfg.frames) if cfg.frames is not None else None,
                mask_dir=cfg.mask_dir,
                params_dir=cfg.params_dir,
                person_id=cfg.person_id,
                smplx_model_path=cfg.smplx_model,
                gender=cfg.gender,
                force=bool(cfg.force),
            )
        print(f"wrote {out} (read it with data=zju_mocap data.protocol=null data.root={out})")

    _main()
    return 0


if __name__ == "__main__":
    sys.exit(main())

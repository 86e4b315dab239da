"""A short training (the training entry point's `run`) on an EasyMocap-layout capture reaches the same PSNR as on the
same capture in the ZJU-MoCap layout (the synthetic studio with the procedural body, rewritten in EasyMocap's layout
with the JPEG files copied, calibration YAML through cv2.FileStorage and JSON parameters)."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np
from test_easymocap import write_calibration, write_json

from framework.data.studio import StudioSettings, generate
from framework.data.zju.reader import ZjuSequence

COMMON = [
    "+experiment=paper_full",
    "body=procedural",
    "data.body=procedural",
    "data.downscale=1",
    "data.test_views=[3]",
    "trainer.max_steps=30",
    "stages.stage1_steps=10",
    "gaussians.num=300",
    "deformer.grid_resolution=12",
    "trainer.val_every=30",
    "callbacks.checkpoint_every=30",
    "callbacks.image_every=1000",
    "callbacks.progress_bar=false",
    "eval.splits=[novel_view]",
    "eval.metrics=[psnr]",
    "metric=novel_view/psnr",
    "logger=none",
    "threads=1",
]


def zju_to_easymocap(src: Path, dst: Path) -> None:
    """The studio's ZJU-layout sequence as EasyMocap would leave it (camera folders named 01.., stems 000000..)."""
    seq = ZjuSequence(src)
    names = [f"{c + 1:02d}" for c in range(seq.num_views)]
    cams = seq.cameras
    write_calibration(dst, names, cams.K, cams.D, cams.R, cams.T_m)
    for f in range(seq.num_frames):
        for c, n in enumerate(names):
            for folder, path in (("images", seq.image_path(f, c)), ("mask", seq.mask_path(f, c, "mask"))):
                (dst / folder / n).mkdir(parents=True, exist_ok=True)
                shutil.copyfile(path, dst / folder / n / f"{f:06d}{path.suffix}")
        p = seq.params(f)
        write_json(
            dst / "output" / "smpl" / f"{f:06d}.json",
            [{"id": 0, **{k: np.asarray(p[k]).reshape(1, -1) for k in ("Rh", "Th", "poses", "shapes")}}],
        )
        write_json(dst / "output" / "vertices" / f"{f:06d}.json", [{"id": 0, "vertices": seq.vertices(f)}])


def _train(tmp_path: Path, name: str, *overrides: str) -> float:
    """The training entry point's `run` in this process (saves a second interpreter start per run)."""
    import torch
    from hydra import compose, initialize_config_module

    from framework.train import run

    out = tmp_path / name
    with initialize_config_module(config_module="framework.conf", version_base="1.3"):
        cfg = compose("train", [*COMMON, f"paths.root={out}", f"paths.output_dir={out}", *overrides])
    threads = torch.get_num_threads()
    try:
        psnr = run(cfg)
    finally:
        torch.set_num_threads(threads)
    with open(out / "eval" / "per_frame.csv") as f:
        rows = list(csv.DictReader(f))
    assert rows and all(r["split"] == "novel_view" and r["view"] == "3" for r in rows)
    assert abs(psnr - np.mean([float(r["psnr"]) for r in rows])) < 1e-6
    return psnr


def test_same_psnr_in_both_layouts(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(tmp_path / "cache"))
    settings = StudioSettings(resolution=32, num_views=4, num_frames=4, body="procedural", supersample=1)
    zju = generate(settings, tmp_path / "zju", workers=1, progress=False)
    zju_to_easymocap(zju, tmp_path / "easymocap")
    psnr_zju = _train(
        tmp_path, "run_zju", "data=zju_mocap", f"data.root={zju}", "data.protocol=null", "data.train_views=[0,1,2]"
    )
    psnr_em = _train(tmp_path, "run_em", "data=easymocap", f"data.root={tmp_path / 'easymocap'}")
    print(f"novel-view PSNR: zju {psnr_zju:.4f} dB, easymocap {psnr_em:.4f} dB")
    assert psnr_zju > 12.0, psnr_zju  # it rendered the subject, not nothing
    assert abs(psnr_em - psnr_zju) < 0.01, (psnr_em, psnr_zju)

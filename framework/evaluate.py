"""Evaluation: PSNR / SSIM / LPIPS per split and per image, on whole images (background included, the paper's
numbers) and inside the image of the body's 3D box (the Neural Body / Animatable NeRF protocol most peers report;
`framework.evaluation.body_box`) when the dataset knows the body's vertices.

`python -m framework.evaluate ckpt=PATH [splits=[novel_view,novel_pose]] [metrics=[psnr,ssim,lpips_alex]]`
writes `per_frame.csv`, `summary.json` and `summary.md` and prints the summary table. Also run at the end of training.
Summary keys: "<split>/<metric>" (whole image) and "<split>/bbox/<metric>" (body box); summary.json holds them as
evaluate_module returns them, for tools that read an evaluation back (tools/compact_point.py).
"""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from framework.atomic import atomic_path, atomic_write_text
from framework.errors import SplatrigError, reported_as_message
from framework.lightning.trained_model import data_overrides, datamodule_for, load_module
from framework.paths import beside_checkpoint
from framework.plugins import format_table, load_plugins
from framework.registry import METRICS


def _metric_objects(names: list[str]) -> dict[str, Any]:
    load_plugins()
    metrics = {}
    for name in names:
        entry = METRICS.entry(name)
        reason = entry.unavailable_reason()
        if reason is not None:
            print(f"[splatrig] metric '{name}' skipped: {reason}", file=sys.stderr)
            continue
        metrics[name] = entry.cls()
    return metrics


@torch.no_grad()
def evaluate_module(
    module,
    datamodule,
    splits: list[str],
    metric_names: list[str],
    out_dir: Path,
    logger=None,
    step: int = 0,
    save_images: int = 4,
) -> dict[str, float]:
    """Returns {"<split>/<metric>": mean}; writes per_frame.csv, summary.json (the returned dict), summary.md and a
    few render|gt|error PNGs."""
    import imageio.v3 as iio

    from framework.lightning.data import collate_frames

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    metrics = _metric_objects(metric_names)
    module.eval()
    rows: list[dict[str, Any]] = []
    summary: dict[str, float] = {}
    has_box = False
    for split in splits:
        try:
            dataset = datamodule.split(split)
        except SplatrigError as exc:
            print(f"[splatrig] split '{split}' skipped: {exc}", file=sys.stderr)
            continue
        values: dict[str, list[float]] = {m: [] for m in metrics}
        values.update({f"bbox/{m}": [] for m in metrics})
        image_every = max(len(dataset) // max(save_images, 1), 1)
        for i in tqdm(range(len(dataset)), desc=f"eval {split}", unit="img", leave=False):
            batch = collate_frames([dataset[i]]).to(module.device)
            rgb = module.render_batch(batch).render.rgb.clamp(0, 1)
            row: dict[str, Any] = {
                "split": split,
                "frame": int(batch.frame[0]),
                "view": -1 if batch.view is None else int(batch.view[0]),
            }
            if not rows:
                _drop_metrics_that_reject(metrics, rgb, batch.image)
            for name, metric in metrics.items():
                v = float(metric(rgb, batch.image)[0])
                values[name].append(v)
                row[name] = v
            for name, v in _body_box_metrics(dataset, batch, rgb, metrics).items():
                has_box = True
                values[f"bbox/{name}"].append(v)
                row[f"bbox_{name}"] = v
            rows.append(row)
            if i % image_every == 0 and save_images:
                err = (rgb[0] - batch.image[0]).abs().mean(-1, keepdim=True).expand(-1, -1, 3) * 4
                grid = torch.cat([rgb[0], batch.image[0], err.clamp(0, 1)], dim=1)
                iio.imwrite(out_dir / f"{split}_{i:05d}.png", (grid.cpu().numpy() * 255).round().astype("uint8"))
                writer = getattr(logger, "experiment", None)
                if writer is not None and hasattr(writer, "add_image"):
                    writer.add_image(f"eval_{split}/render|gt|error/{i:05d}", grid.permute(2, 0, 1).cpu(), step)
        for name, vals in values.items():
            finite = [v for v in vals if math.isfinite(v)]
            if finite:
                summary[f"{split}/{name}"] = float(sum(finite) / len(finite))
    with atomic_path(out_dir / "per_frame.csv") as tmp, open(tmp, "w", newline="") as f:
        fields = ["split", "frame", "view", *metrics, *([f"bbox_{m}" for m in metrics] if has_box else [])]
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)
    atomic_write_text(out_dir / "summary.json", json.dumps(summary, indent=1) + "\n")
    table = summary_table(summary, splits, list(metrics))
    atomic_write_text(out_dir / "summary.md", table + "\n")  # written last: its presence marks a finished evaluation
    print("\n" + table)
    if logger is not None and hasattr(logger, "experiment") and hasattr(logger.experiment, "add_scalar"):
        for key, value in summary.items():
            logger.experiment.add_scalar(f"eval/{key}", value, step)
    return summary


def _drop_metrics_that_reject(metrics: dict[str, Any], rgb: torch.Tensor, image: torch.Tensor) -> None:
    """Leave out, with a note, the metrics that cannot score images like these (LPIPS needs >= 31 px on a side)."""
    for name, metric in list(metrics.items()):
        try:
            metric(rgb, image)
        except (ValueError, SplatrigError) as exc:
            print(f"[splatrig] metric '{name}' skipped: {exc}", file=sys.stderr)
            del metrics[name]


def _body_box_metrics(dataset, batch, rgb, metrics: dict[str, Any]) -> dict[str, float]:
    """Metrics inside the body box of this (frame, view), or {} when the dataset has no body vertices."""
    from framework.evaluation.body_box import box_mask, box_region_metrics

    box = dataset.body_box(int(batch.frame[0]))
    if box is None:
        return {}
    cams = batch.cameras
    mask = box_mask(
        box, cams.K[0].double().cpu().numpy(), cams.world_to_cam[0].double().cpu().numpy(), cams.width, cams.height
    )
    return box_region_metrics(rgb[0], batch.image[0], mask, metrics)


def summary_table(summary: dict[str, float], splits: list[str], metrics: list[str]) -> str:
    rows = []
    for split in splits:
        for label, prefix in ((split, f"{split}/"), (f"{split} (body box)", f"{split}/bbox/")):
            if any(f"{prefix}{m}" in summary for m in metrics):
                rows.append(
                    (label, *[f"{summary[f'{prefix}{m}']:.4f}" if f"{prefix}{m}" in summary else "-" for m in metrics])
                )
    return format_table(rows, ("split", *metrics))


def main() -> int:
    from omegaconf import DictConfig

    from framework.cli import hydra_main

    @hydra_main("evaluate")
    def _main(cfg: DictConfig) -> None:
        with reported_as_message():
            evaluate_from_config(cfg)

    _main()
    return 0


def evaluate_from_config(cfg) -> Path:
    """What `python -m framework.evaluate` does with its composed config; returns the output folder."""
    from framework.config_checks import check_evaluate_config

    check_evaluate_config(cfg)
    module = load_module(cfg.ckpt)
    dm = datamodule_for(module, data_overrides(cfg))
    splits = list(cfg.splits) if cfg.splits else list(module.settings.eval.splits)
    metrics = list(cfg.metrics) if cfg.metrics else list(module.settings.eval.metrics)
    record_as = cfg.get("record_as")
    run_dir = Path(str(cfg.ckpt)).resolve().parent.parent  # <run>/checkpoints/<file>
    if record_as:
        if len(splits) != 1:
            raise SplatrigError(f"record_as={record_as}: records one split (splits=[novel_pose]), got {splits}")
        if not (run_dir / "results.json").is_file():
            raise SplatrigError(
                f"record_as={record_as}: {run_dir} has no results.json to record into; record_as takes a training "
                f"run's checkpoint (<run>/checkpoints/final.ckpt)"
            )
    out = Path(cfg.out_dir) if cfg.out_dir else beside_checkpoint(cfg.ckpt, "eval")
    summary = evaluate_module(module, dm, splits, metrics, out)
    print(f"[splatrig] evaluation written to {out}")
    if record_as:
        from framework.evaluation.run_record import metrics_from_summary, record_metrics

        measured = metrics_from_summary(summary).get(splits[0])
        if not measured:
            raise SplatrigError(f"record_as={record_as}: split {splits[0]} measured nothing; nothing recorded")
        path = record_metrics(run_dir, str(record_as), measured)
        print(f"[splatrig] recorded as metrics.{record_as} in {path}")
    return out


if __name__ == "__main__":
    main()

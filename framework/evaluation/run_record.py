"""The per-run results record: `<run dir>/results.json`, written at the end of training, read by `framework.report`.

One JSON object per run, so a sweep's runs can be collected from any number of sweep directories (a sweep run in
parts) and reports of several kinds read the same data. Schema "splatrig.run/1" (records
written before the cost fields existed lack them; readers treat a missing field as not measured):

    schema          "splatrig.run/1"
    experiment      the config's task_name (the Table 4 row, e.g. "no_corrector")
    config_name     Hydra's primary config ("train", or a sweep such as "ablations")
    overrides       the job's command-line / sweep overrides, as Hydra lists them (["+experiment=...", "seed=1", ...])
    seed            the run's seed
    profile, data   the hardware profile's name and the dataset's registry name
    steps           training steps done; max_steps: the steps asked for
    train_seconds   wall time of training (trainer.fit); run_seconds: of the whole run (setup, training, evaluation)
    train_cpu_seconds  CPU time of training, all threads (on a shared machine a steadier measure than wall time)
    num_gaussians   Gaussians at the end of training
    peak_rss_mib    peak resident memory of the fit loop (MiB); cuda_peak_mib: peak allocated CUDA memory or null
    seconds_per_step  train_seconds / steps
    stage_seconds   {"stage1"|"stage2": {"steps", "seconds", "steps_per_second"}}: each stage's share of this fit
                    (validation included; on CUDA the clock is read after a synchronise at each boundary)
    render_fps      {"novel_pose": fps, "novel_view": fps, "split", "frames", "warmup", "device"}: render speed of the
                    final model as tools/bench_render.py measures it (framework.evaluation.run_cost); fps are null
                    when skipped (eval.fps_frames=0) or not applicable (no body: no novel-pose fps)
    model_bytes     bytes of the learned tensors; checkpoint_bytes: size on disk of `checkpoint` (final.ckpt, or
                    last.ckpt when no blend weights were baked; both hold the optimizer state too)
    metrics         {split: {"image": {metric: mean}, "body_box": {metric: mean}}}: whole-image metrics (the paper's)
                    and body-box metrics (Neural Body / Animatable NeRF; framework.evaluation.body_box), averaged
                    over the split's images; e.g. metrics["novel_pose"]["body_box"]["psnr"]
    code            {"version": package version, "commit": git commit of the checkout or null}
    created         ISO 8601 time the record was written

Fields added after training (`record_field`; each one's name is listed in `recorded_later`):

    metrics[name]   one more evaluation, e.g. novel_pose_true_poses (tools/record_true_poses.py; `record_metrics`)
    viewer_fps      {"resolution", "device", "warmup", "frames", "num_gaussians", "sh_degree",
                    "paths": {"compiled"|"torch": {"novel_pose": fps, "novel_view": fps}}}: the viewer's frame rate
                    at a square resolution on orbit cameras and random poses (tools/record_fps.py, bench_render's
                    rules): compiled = the compiled CPU kernels and the numba rasterizer, torch = the torch execution
                    and torch_ref (a GPU's torch code on this device); a path whose rasterizer is unavailable holds
                    null fps and its reason
    recorded_later  the names above that this record holds, in the order they were recorded

A record derived from another run's model (tools/compact_point.py: its final checkpoint pruned and refitted) also
holds `derived_from` {"run": the parent's folder name, "step": what made the model, "prune_seconds": wall time}.
"""

from __future__ import annotations

import datetime
import json
import subprocess
from pathlib import Path
from typing import Any

from framework.atomic import atomic_write_text
from framework.errors import SplatrigError

SCHEMA = "splatrig.run/1"
FILENAME = "results.json"
REGIONS = {"image": "", "body_box": "bbox/"}  # region -> the infix of evaluate_module's summary keys


def metrics_from_summary(summary: dict[str, float]) -> dict[str, dict[str, dict[str, float]]]:
    """evaluate_module's {"novel_view/psnr": x, "novel_view/bbox/psnr": y, ...} -> {split: {region: {metric: v}}}."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for key, value in summary.items():
        split, _, rest = key.partition("/")
        region = "body_box" if rest.startswith(REGIONS["body_box"]) else "image"
        name = rest[len(REGIONS[region]) :]
        out.setdefault(split, {}).setdefault(region, {})[name] = float(value)
    return out


def _commit() -> str | None:
    try:
        done = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            text=True,
            capture_output=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    if done.returncode != 0:
        return None
    return done.stdout.strip() or None


def write_run_record(run_dir: Path, **fields: Any) -> Path:
    """Write results.json into `run_dir` (atomically); `fields` are the schema's keys except schema/code/created."""
    from framework import __version__

    record = {
        "schema": SCHEMA,
        **fields,
        "code": {"version": __version__, "commit": _commit()},
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }
    return atomic_write_text(Path(run_dir) / FILENAME, json.dumps(record, indent=1) + "\n")


def record_field(run_dir: Path, key: str, value: Any, recorded_as: str | None = None) -> Path:
    """Set one top-level field of a run's results.json to `value` (written atomically; the rest of the record is
    kept) and list `recorded_as` (default: `key`) in its `recorded_later`, once however often it is recorded."""
    path = Path(run_dir) / FILENAME
    record = load_run_record(path)
    record[key] = value
    done = record.setdefault("recorded_later", [])
    name = key if recorded_as is None else recorded_as
    if name not in done:
        done.append(name)
    return atomic_write_text(path, json.dumps(record, indent=1) + "\n")


def record_metrics(run_dir: Path, name: str, metrics: dict[str, dict[str, float]]) -> Path:
    """Store one more evaluation in a run's results.json as `metrics[name]` ({region: {metric: value}}), e.g. the
    held-out motion evaluated under another protocol after training; the rest of the record is kept."""
    stored = load_run_record(Path(run_dir) / FILENAME).get("metrics") or {}
    return record_field(run_dir, "metrics", {**stored, name: metrics}, recorded_as=name)


def load_run_record(path: Path) -> dict[str, Any]:
    """Read and check one results.json."""
    path = Path(path)
    try:
        record = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise SplatrigError(f"{path}: not valid JSON ({exc}); delete it or re-run that job.") from None
    if record.get("schema") != SCHEMA:
        raise SplatrigError(
            f"{path}: expected a run record with schema '{SCHEMA}', found schema {record.get('schema')!r}; it was "
            f"written by another version, re-run that job with this one."
        )
    return record

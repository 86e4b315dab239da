"""Add "trade-off point P followed by compaction" to a trade-off sweep as its own point, `P_compact`: every run of P
(`+tradeoff=P` among its overrides) is pruned and refitted (`python -m framework.prune`, its defaults), the pruned
model is evaluated on the held-out splits (`python -m framework.evaluate`), and a sibling folder
`<P>_compact_seed<S>` gets the pruned checkpoint and a results.json the trade-off report reads like any other run's.

    python tools/compact_point.py outputs/tradeoff/<part 1> [outputs/tradeoff/<part 2> ...] [--point scene_auto] \
        [framework.prune overrides, e.g. refit_steps=500]

Why: `+scene=auto` keeps only what the scene needs while training; pruning afterwards removes more, and the refit
after it is training too. The new record charges it: train_seconds (and train_cpu_seconds) are the parent's plus
the prune's, peak_rss_mib the larger of the two, num_gaussians and sizes are the pruned model's, metrics its own;
render_fps is left out (tools/record_fps.py times every run's viewer frame rate afterwards). `derived_from` names
the parent. framework.prune runs with `measure=false` (its before/after fps and PSNR are evaluation, not training,
and would be charged as training time; pass measure=true to have them in prune.json anyway).
Runs whose compact folder already holds a results.json are skipped, so an interrupted call continues.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

SPLITS = "[novel_view,novel_pose]"
DROPPED = ("schema", "code", "created", "render_fps", "viewer_fps", "recorded_later", "seconds_per_step")
"""Parent fields the new record does not carry: written anew, measured later (fps), or about the parent's model
only (later recorded evaluations; seconds per step, whose train_seconds no longer holds)."""


@dataclass
class Measured:
    """A finished subprocess: exit status, wall seconds, CPU seconds (user + system, all its threads and children)
    and peak resident memory (MiB)."""

    returncode: int
    seconds: float
    cpu_seconds: float
    peak_rss_mib: float


def run_measured(cmd: list[str], log: Path) -> Measured:
    """Run `cmd` with its output in `log`; its own resource usage comes from os.wait4 (this process's other children
    are not mixed in, as RUSAGE_CHILDREN's maximum would)."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as out:
        start = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
        seconds = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait for it again
    return Measured(proc.returncode, seconds, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024)  # KiB on Linux


def tradeoff_point(record: dict[str, Any]) -> str | None:
    """The run's trade-off point: NAME of `+tradeoff=NAME` among its overrides, or None."""
    for item in record.get("overrides", []):
        key, _, value = item.partition("=")
        if key.lstrip("+~") == "tradeoff":
            return value
    return None


def compact_folder(run: Path, point: str, seed: int) -> Path:
    return run.parent / f"{point}_compact_seed{seed}"


def pending(folders: list[Path], point: str) -> list[tuple[Path, dict[str, Any]]]:
    """(run folder, its record) of every run of `point` below `folders` with a final checkpoint whose compact folder
    holds no results.json yet."""
    runs = []
    for folder in folders:
        for path in sorted(Path(folder).rglob("results.json")):
            record = json.loads(path.read_text())
            run = path.parent
            if (
                tradeoff_point(record) == point
                and (run / "checkpoints" / "final.ckpt").is_file()
                and not (compact_folder(run, point, int(record["seed"])) / "results.json").is_file()
            ):
                runs.append((run, record))
    return runs


def compact_record(
    parent: dict[str, Any],
    parent_name: str,
    point: str,
    prune: Measured,
    evaluate_seconds: float,
    model: dict[str, Any],
    metrics: dict[str, Any],
    refit_steps: int | None,
) -> dict[str, Any]:
    """The fields of the compact run's results.json (write_run_record adds schema, code, created): the parent's
    record with the point renamed `<point>_compact`, the prune's cost added to the training's, and the pruned
    model's size (`model`: num_gaussians, model_bytes, checkpoint, checkpoint_bytes) and `metrics`."""

    def plus(key: str, extra: float) -> float | None:
        return None if parent.get(key) is None else round(float(parent[key]) + extra, 2)

    old, new = f"+tradeoff={point}", f"+tradeoff={point}_compact"
    if old not in parent.get("overrides", []):
        raise ValueError(f"{parent_name}: its overrides hold no {old}")
    fields = {k: v for k, v in parent.items() if k not in DROPPED}
    peaks = [p for p in (parent.get("peak_rss_mib"), prune.peak_rss_mib) if p is not None]
    fields.update(
        experiment=f"{parent['experiment']}_compact",
        overrides=[new if item == old else item for item in parent["overrides"]],
        train_seconds=plus("train_seconds", prune.seconds),
        train_cpu_seconds=plus("train_cpu_seconds", prune.cpu_seconds),
        run_seconds=plus("run_seconds", prune.seconds + evaluate_seconds),
        peak_rss_mib=round(max(peaks), 1),
        num_gaussians=int(model["num_gaussians"]),
        model_bytes=int(model["model_bytes"]),
        checkpoint=str(model["checkpoint"]),
        checkpoint_bytes=int(model["checkpoint_bytes"]),
        metrics=metrics,
        derived_from={
            "run": parent_name,
            "step": "framework.prune",
            "prune_seconds": round(prune.seconds, 2),
            "prune_cpu_seconds": round(prune.cpu_seconds, 2),
            "prune_peak_rss_mib": round(prune.peak_rss_mib, 1),
            "refit_steps": refit_steps,
        },
    )
    return fields


def pruned_model(ckpt: Path) -> dict[str, Any]:
    """Gaussians and learned bytes of a pruned checkpoint, counted as a training run counts its own
    (`framework.evaluation.run_cost.model_bytes`, on the model as loaded, before any weights are baked)."""
    from framework.evaluation.run_cost import model_bytes
    from framework.lightning.trained_model import load_module

    module = load_module(ckpt, "cpu")
    return {
        "num_gaussians": int(module.avatar.gaussians.num),
        "model_bytes": model_bytes(module),
        "checkpoint": ckpt.name,
        "checkpoint_bytes": ckpt.stat().st_size,
    }


def _last_line(log: Path) -> str:
    lines = log.read_text(errors="replace").strip().splitlines()
    return lines[-1] if lines else "(no output)"


def entry_point(verb: str, *overrides: str) -> list[str]:
    """The command line of `python -m framework.<verb> key=value ...` in this interpreter."""
    return [sys.executable, "-m", f"framework.{verb}", *overrides]


def compact_run(run: Path, record: dict[str, Any], point: str, extra: list[str]) -> str:
    """Prune, evaluate and record one run; returns a one-line status."""
    from framework.evaluation.run_record import metrics_from_summary, write_run_record

    out = compact_folder(run, point, int(record["seed"])).resolve()
    ckpt = out / "checkpoints" / "final.ckpt"
    measure = [] if any(x.split("=", 1)[0] == "measure" for x in extra) else ["measure=false"]
    steps = {
        "prune": entry_point(
            "prune",
            f"ckpt={(run / 'checkpoints' / 'final.ckpt').resolve()}",
            f"out={ckpt}",
            f"json={out / 'prune.json'}",
            *measure,
            *extra,
        ),
        "evaluate": entry_point("evaluate", f"ckpt={ckpt}", f"splits={SPLITS}", f"out_dir={out / 'eval'}"),
    }
    measured: dict[str, Measured] = {}
    for name, cmd in steps.items():  # in order: the evaluation reads the pruned checkpoint
        log = out / f"{name}.log"
        measured[name] = run_measured(cmd, log)
        if measured[name].returncode != 0:
            return f"{name} failed ({log}): {_last_line(log)}"
    summary = json.loads((out / "eval" / "summary.json").read_text())
    report = json.loads((out / "prune.json").read_text())
    refit_steps = (report.get("refit") or {}).get("steps", 0)
    prune = measured["prune"]
    fields = compact_record(
        record,
        run.name,
        point,
        prune,
        measured["evaluate"].seconds,
        pruned_model(ckpt),
        metrics_from_summary(summary),
        refit_steps,
    )
    write_run_record(out, **fields)
    psnr = fields["metrics"].get("novel_pose", {}).get("image", {}).get("psnr")
    return (
        f"{record['num_gaussians']} -> {fields['num_gaussians']} Gaussians, prune {prune.seconds:.0f} s, "
        f"novel-pose PSNR {psnr if psnr is None else round(psnr, 2)}: {out.name}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", help="sweep folders (searched for results.json), then prune overrides")
    ap.add_argument("--point", default="scene_auto", help="the trade-off point to compact")
    args = ap.parse_args(argv)
    folders = [Path(x) for x in args.folders if "=" not in x]
    extra = [x for x in args.folders if "=" in x]  # key=value: passed on to framework.prune
    runs = pending(folders, args.point)
    print(f"{len(runs)} runs of {args.point} to compact", flush=True)
    for i, (run, record) in enumerate(runs, 1):
        print(f"[{i}/{len(runs)}] {run.name}: {compact_run(run, record, args.point, extra)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""How far compaction can take one trained model: several settings of `python -m framework.prune` applied to the
same checkpoint, each compact model's PSNR against a reference run (paper_full) and its novel-pose frame rate timed
interleaved against that run; a table, a CSV and a picture with the target region.

    python tools/compaction_trade.py --reference <paper_full run>/checkpoints/final.ckpt \\
        --ckpt <auto run>/checkpoints/final.ckpt --out outputs/compaction_trade
    python tools/compaction_trade.py ... --setting kept=fold_tolerance=null \\
        --setting fast=prune_tolerance=0.045,refit_steps=600

Why: `+scene=auto` and the compaction pick one point of a trade between frame rate, size and PSNR. This shows the
others on the same model, so a choice (or a missed target) can be read off one picture instead of argued.

Default settings: the model as trained; F_a kept whole (`fold_tolerance=null`); the partial fold at 1/255, 2/255 and
3/255; F_a folded whole (`fold_tolerance=1.0`); pruning further, to 0.045 and 0.06 RMS. A setting is `name=key=value,
key=value` with `framework.prune`'s keys (values as YAML: `null`, numbers, `auto`). Each compact model goes to
`<out>/<name>.ckpt` with its report `<out>/<name>.json`; a setting whose two files exist is not compacted again, so an
interrupted run resumes. Frame rates: `framework.lightning.trained_model.interleaved_fps` (all models in one process,
round by round, medians). Targets (`--target-fps`, `--budget-db`) default to `docs/results/scene_adaptive.md`'s for
the simpler scenes: 1.5x the reference's novel-pose frame rate at less than 0.3 dB.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as framework.train: the timing shares the machine

import torch  # noqa: E402
import yaml  # noqa: E402

AS_TRAINED = "as trained"
DEFAULT_SETTINGS: dict[str, dict] = {
    AS_TRAINED: {},
    "F_a kept whole": {"fold_tolerance": None},
    "fold 1/255": {"fold_tolerance": 1 / 255},
    "fold 2/255": {"fold_tolerance": 2 / 255},
    "fold 3/255": {"fold_tolerance": 3 / 255},
    "F_a folded whole": {"fold_tolerance": 1.0},
    "prune 0.045": {"prune_tolerance": 0.045},
    "prune 0.06": {"prune_tolerance": 0.06},
}
PRUNE_KEYS = (
    "fold_tolerance",
    "prune_tolerance",
    "refit_steps",
    "prune_rounds",
    "min_weight",
    "sh_tolerance",
    "max_frames",
)


@dataclass
class TradeRow:
    setting: str
    overrides: str
    num_gaussians: int
    corrector_rows: int  # Gaussians F_a still runs on at a novel pose (0: folded whole or none)
    smaller: float  # reference's learned bytes / this model's
    psnr_novel_view: float  # dB, against the reference
    psnr_novel_pose: float
    novel_pose_fps: float
    fps_ratio: float  # against the reference, interleaved

    def meets(self, target_fps: float, budget_db: float) -> bool:
        """At least `target_fps` times the reference's frame rate, losing less than `budget_db` (0: no loss)."""
        loss = -min(self.psnr_novel_view, self.psnr_novel_pose)
        return self.fps_ratio >= target_fps and (loss < budget_db or loss <= 0.0)


def target_words(target_fps: float, budget_db: float) -> str:
    return f">= {target_fps:g}x at " + (f"< {budget_db:g} dB loss" if budget_db > 0 else "no loss")


def parse_setting(text: str) -> tuple[str, dict]:
    """`name=key=value,key=value` -> (name, {key: value}); one clear error for anything else."""
    name, sep, rest = text.partition("=")
    if not sep or not name or not rest:
        raise SystemExit(f"--setting {text!r}: expected NAME=KEY=VALUE[,KEY=VALUE], e.g. kept=fold_tolerance=null.")
    options = {}
    for item in rest.split(","):
        key, sep, value = item.partition("=")
        if not sep or key not in PRUNE_KEYS:
            raise SystemExit(f"--setting {text!r}: {key!r} is not one of framework.prune's keys {list(PRUNE_KEYS)}.")
        options[key] = yaml.safe_load(value)
    return name, options


def _file_name(setting: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in setting)


def _yaml_value(value) -> str:
    """As a command line would write it: null, a short number, or the word."""
    if value is None:
        return "null"
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def _corrector_rows(ckpt: Path) -> int:
    """Rows F_a runs on in a stored model: none without a corrector, `active_rows` after a partial fold, else all."""
    sd = torch.load(ckpt, map_location="cpu", weights_only=False)["state_dict"]
    if "avatar.corrector.head.weight" not in sd:
        return 0
    rows = sd.get("avatar.corrector.active_rows")
    return int(rows.numel()) if rows is not None and rows.numel() else int(sd["avatar.gaussians.params.means"].shape[0])


def compact_all(ckpt: Path, out: Path, settings: dict[str, dict], device: str) -> dict[str, tuple[Path, dict]]:
    """Each setting's compact model and report (as a dict), made once: a model whose report names the same source
    and options is reused (an interrupted run resumes), anything else is compacted again. The report's "after" is
    the compact model's own measure (sizes and PSNR); the source is measured once, by `trade`, not per setting."""
    from framework.compaction.compact import measure_module, prune_checkpoint
    from framework.lightning.trained_model import datamodule_for, load_module

    made = {}
    for name, options in settings.items():
        if name == AS_TRAINED:
            continue
        path, report_path = out / f"{_file_name(name)}.ckpt", out / f"{_file_name(name)}.json"
        made_by = {"source": str(ckpt.resolve()), "options": options}
        stored = json.loads(report_path.read_text()) if report_path.is_file() else {}
        if not (path.is_file() and stored.get("made_by") == made_by):
            print(f"[compaction_trade] {name}: framework.prune {options or '(defaults)'}", flush=True)
            report = prune_checkpoint(ckpt, path, measure=False, device=device, **options)
            compact = load_module(path, map_location=device)
            after = measure_module(compact, datamodule_for(compact), repeats=0, file_bytes=path.stat().st_size)
            stored = {"made_by": made_by, **report.to_dict(), "after": asdict(after)}
            tmp = report_path.with_suffix(".json.tmp")
            tmp.write_text(json.dumps(stored, indent=1))
            os.replace(tmp, report_path)
        made[name] = (path, stored)
    return made


def trade(
    reference: Path,
    ckpt: Path,
    out: Path,
    settings: dict[str, dict],
    warmup: int,
    repeats: int,
    rounds: int,
    device: str,
    rasterizer: str | None = None,
) -> list[TradeRow]:
    """Compact, measure PSNR, time interleaved; one row per setting (the model as trained included if asked)."""
    from framework.compaction.compact import measure_module
    from framework.lightning.trained_model import datamodule_for, interleaved_fps, load_module

    out.mkdir(parents=True, exist_ok=True)
    made = compact_all(ckpt, out, settings, device)
    ref_module = load_module(reference, map_location=device)
    ref = measure_module(ref_module, datamodule_for(ref_module), repeats=0)
    paths = {name: made[name][0] if name in made else ckpt for name in settings}
    measures = {}
    for name, path in paths.items():
        if name in made:
            measures[name] = made[name][1]["after"]
        else:
            module = load_module(path, map_location=device)
            measures[name] = asdict(measure_module(module, datamodule_for(module), repeats=0))
    print(f"[compaction_trade] timing {len(paths) + 1} models interleaved, {rounds} rounds", flush=True)
    fps = interleaved_fps({"reference": reference, **paths}, warmup, repeats, rounds, device, rasterizer)
    rows = []
    for name, path in paths.items():
        m = measures[name]
        rows.append(
            TradeRow(
                setting=name,
                overrides=" ".join(f"{k}={_yaml_value(v)}" for k, v in settings[name].items()) or "-",
                num_gaussians=int(m["num_gaussians"]),
                corrector_rows=_corrector_rows(path),
                smaller=ref.model_bytes / m["model_bytes"],
                psnr_novel_view=m["psnr"]["novel_view"] - ref.psnr["novel_view"],
                psnr_novel_pose=m["psnr"]["novel_pose"] - ref.psnr["novel_pose"],
                novel_pose_fps=fps[name][0],
                fps_ratio=fps[name][0] / fps["reference"][0],
            )
        )
    return rows


def markdown(rows: list[TradeRow], target_fps: float, budget_db: float) -> str:
    lines = [
        "| setting | overrides | Gaussians | F_a rows | smaller | PSNR novel view / novel pose dB "
        f"| novel-pose fps | meets {target_words(target_fps, budget_db)} |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.setting} | `{r.overrides}` | {r.num_gaussians} | {r.corrector_rows} | {r.smaller:.2f}x | "
            f"{r.psnr_novel_view:+.2f} / {r.psnr_novel_pose:+.2f} | {r.novel_pose_fps:.1f} "
            f"({r.fps_ratio:.2f}x) | {'yes' if r.meets(target_fps, budget_db) else 'no'} |"
        )
    return "\n".join(lines)


def write_csv(rows: list[TradeRow], path: Path) -> None:
    from framework.atomic import atomic_path

    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(asdict(rows[0])))
        writer.writeheader()
        writer.writerows(asdict(r) for r in rows)


def plot(rows: list[TradeRow], path: Path, target_fps: float, budget_db: float, title: str) -> Path:
    """PSNR change against frame-rate ratio, novel view and novel pose per setting, the target region shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from framework.reporting.figures import save_png

    fig, ax = plt.subplots(figsize=(7.5, 5.0))
    xs = [r.fps_ratio for r in rows]
    ys = [v for r in rows for v in (r.psnr_novel_view, r.psnr_novel_pose)]
    x_hi = max(max(xs), target_fps) * 1.08
    y_lo = min(min(ys), -budget_db) - 0.1
    ax.fill_between(
        [target_fps, x_hi],
        -budget_db,
        max(max(ys), 0.0) + 0.1,
        color="tab:green",
        alpha=0.12,
        label=f"target: {target_words(target_fps, budget_db)}",
    )
    ax.axhline(0.0, color="grey", lw=0.8)
    ax.axvline(1.0, color="grey", lw=0.8)
    for i, r in enumerate(rows):
        ax.plot([r.fps_ratio] * 2, [r.psnr_novel_view, r.psnr_novel_pose], color="grey", lw=0.8, zorder=1)
        ax.scatter([r.fps_ratio], [r.psnr_novel_view], marker="o", color="tab:blue", zorder=2)
        ax.scatter([r.fps_ratio], [r.psnr_novel_pose], marker="x", color="tab:red", zorder=2)
        # labels above the upper marker and below the lower one in turn, so neighbours in x do not overprint
        upper = i % 2 == 0
        y = max(r.psnr_novel_view, r.psnr_novel_pose) if upper else min(r.psnr_novel_view, r.psnr_novel_pose)
        ax.annotate(
            r.setting, (r.fps_ratio, y), textcoords="offset points", xytext=(4, 5 if upper else -12), fontsize=8
        )
    ax.scatter([], [], marker="o", color="tab:blue", label="novel view")
    ax.scatter([], [], marker="x", color="tab:red", label="novel pose")
    ax.set_xlim(min(min(xs), 1.0) - 0.05, x_hi)
    ax.set_ylim(y_lo, max(max(ys), 0.0) + 0.1)
    ax.set_xlabel("novel-pose frame rate / reference's (interleaved)")
    ax.set_ylabel("PSNR against the reference, dB")
    ax.set_title(title, fontsize=10)
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    save_png(fig, path)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reference", type=Path, required=True, help="the run to compare against (paper_full's ckpt)")
    ap.add_argument("--ckpt", type=Path, required=True, help="the trained model to compact (not a compact one)")
    ap.add_argument("--out", type=Path, default=Path("outputs/compaction_trade"))
    ap.add_argument(
        "--setting",
        action="append",
        default=[],
        metavar="NAME=KEY=VALUE[,KEY=VALUE]",
        help="replaces the default settings (repeat it); `as trained` is always included",
    )
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--rounds", type=int, default=15, help="interleaved rounds of frame-rate timing (medians)")
    ap.add_argument(
        "--rasterizer",
        default=None,
        help="time every model's frames with this backend (e.g. numba); default: the one it trained with",
    )
    ap.add_argument("--target-fps", type=float, default=1.5)
    ap.add_argument("--budget-db", type=float, default=0.3)
    args = ap.parse_args(argv)
    for flag, path in (("--reference", args.reference), ("--ckpt", args.ckpt)):
        if not path.is_file():
            raise SystemExit(f"{flag} {path}: no such checkpoint file (look in a run's checkpoints/ folder).")
    settings = dict([parse_setting(s) for s in args.setting]) if args.setting else dict(DEFAULT_SETTINGS)
    settings = {AS_TRAINED: {}, **settings}
    from framework.runtime import default_device

    device = default_device()
    rows = trade(
        args.reference, args.ckpt, args.out, settings, args.warmup, args.repeats, args.rounds, device, args.rasterizer
    )
    table = markdown(rows, args.target_fps, args.budget_db)
    backend = f"rasterizer {args.rasterizer}" if args.rasterizer else "each model's own rasterizer"
    header = (
        f"# compaction trade of `{args.ckpt}` against `{args.reference}`\n\ndevice {device}; {backend}; frame "
        f"rates interleaved over {args.rounds} rounds (medians)\n\n"
    )
    (args.out / "compaction_trade.md").write_text(header + table + "\n")
    write_csv(rows, args.out / "compaction_trade.csv")
    title = "/".join(args.ckpt.resolve().parts[-4:-2]) + " against " + "/".join(args.reference.resolve().parts[-4:-2])
    png = plot(rows, args.out / "compaction_trade.png", args.target_fps, args.budget_db, title)
    print(table)
    print(f"[compaction_trade] written: {args.out / 'compaction_trade.md'}, {args.out / 'compaction_trade.csv'}, {png}")


if __name__ == "__main__":
    sys.exit(main())

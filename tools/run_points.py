"""Run a sweep's points one job at a time, each job in its own process, into one folder per part; then time each
finished model's viewer frames (tools/record_fps.py). What the published trade-off was measured with.

    python tools/run_points.py outputs/tradeoff/part1 --points baseline sh0 steps_half --seeds 0 1
    python tools/run_points.py outputs/tradeoff/part1 --points ... -- profile=gpu     # Hydra overrides after --

Why not `hydra/launcher=submitit_local`: it gives each job its own process (so peak memory is the job's own) but
starts every job of the sweep at once, so on a small machine the jobs share its cores and their training times
measure the crowd, not the point. Here a job starts when the one before has ended. Finished jobs (a results.json in
`<part>/<point>_seed<s>/`) are skipped, so an interrupted part continues where it stopped; `touch <part>/STOP` ends
the part after the running job. `--true-poses` also scores each run on the realistic studio's true poses, the split
the trade-off report then judges novel poses on.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

TOOLS = Path(__file__).resolve().parent
SWEEP_DEFAULTS = ["profile=ablation", "data=synthetic_studio_realistic", "callbacks.progress_bar=false"]


def job_command(part: Path, point: str, seed: int, sweep: str, group: str, overrides: list[str]) -> list[str]:
    """The `framework.train` command of one job: the sweep's config, one point and one seed, its folder in `part`."""
    return [
        sys.executable,
        "-m",
        "framework.train",
        f"--config-name={sweep}",
        *SWEEP_DEFAULTS,
        f"seed={seed}",
        f"+{group}={point}",
        f"hydra.sweep.dir={part}",
        f"hydra.sweep.subdir=${{hydra:runtime.choices.{group}}}_seed${{seed}}",
        *overrides,
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("part", type=Path, help="the part's folder (created)")
    ap.add_argument("--points", nargs="+", required=True, help="options of the sweep's group, e.g. baseline sh0")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    ap.add_argument("--sweep", default="tradeoff", help="the sweep's config name (sweeps/<name>.yaml)")
    ap.add_argument("--group", default="tradeoff", help="the config group the points are options of")
    ap.add_argument("--no-fps", action="store_true", help="skip tools/record_fps.py after each job")
    ap.add_argument(
        "--true-poses",
        action="store_true",
        help="after each job, also score the held-out motion on the studio's true poses (tools/record_true_poses.py)",
    )
    ap.add_argument("overrides", nargs="*", help="Hydra overrides for every job (after --)")
    args = ap.parse_args(argv)
    part = args.part.resolve()
    part.mkdir(parents=True, exist_ok=True)
    jobs = [(p, s) for p in args.points for s in args.seeds]
    for i, (point, seed) in enumerate(jobs, 1):
        run = part / f"{point}_seed{seed}"
        if (part / "STOP").exists():
            print(f"{part / 'STOP'} exists: stopping before {run.name}")
            return 0
        if not (run / "results.json").is_file():
            log = part / f"{run.name}.log"
            start = time.monotonic()
            with log.open("w") as out:
                cmd = job_command(part, point, seed, args.sweep, args.group, args.overrides)
                done = subprocess.run(cmd, stdout=out, stderr=subprocess.STDOUT)
            minutes = (time.monotonic() - start) / 60
            status = "ok" if done.returncode == 0 else f"failed (exit {done.returncode}; see {log})"
            print(f"[{i}/{len(jobs)}] {run.name}: {status}, {minutes:.1f} min", flush=True)
        if (run / "results.json").is_file():
            after = [] if args.no_fps else ["record_fps.py"]
            after += ["record_true_poses.py"] if args.true_poses else []
            for tool in after:  # each skips a run that already holds its field
                subprocess.run([sys.executable, str(TOOLS / tool), str(run)], check=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())

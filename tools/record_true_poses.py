"""Evaluate every finished run under the given sweep folders on the held-out motion with the studio's true poses
(ground_truth/params and ground_truth/vertices, the poses its images were rendered from) and record the result in
each run's results.json as `novel_pose_true_poses`; the Table 4 report then shows that split beside the others.

    python tools/record_true_poses.py outputs/ablations/<part 1> [outputs/ablations/<part 2> ...]

Why: the realistic studio stores poses with fitting noise, as a real capture does, and the held-out motion is
rendered with those noisy poses. Judging a row on the true poses separates what the model learned from that noise.
Runs that already hold the split are skipped, so an interrupted call continues where it stopped.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

SPLIT = "novel_pose_true_poses"
OVERRIDES = ["splits=[novel_pose]", "+data.params_dir=ground_truth/params", "+data.vertices_dir=ground_truth/vertices"]


def pending(folders: list[Path]) -> list[Path]:
    """Run folders with a results.json and a final checkpoint that do not hold the split yet."""
    runs = []
    for folder in folders:
        for record in sorted(folder.rglob("results.json")):
            run = record.parent
            if (
                SPLIT not in json.loads(record.read_text()).get("metrics", {})
                and (run / "checkpoints/final.ckpt").is_file()
            ):
                runs.append(run)
    return runs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", type=Path, help="sweep folders (searched for results.json)")
    folders = ap.parse_args().folders
    runs = pending(folders)
    print(f"{len(runs)} runs to evaluate with the true poses")
    for i, run in enumerate(runs, 1):
        cmd = [
            sys.executable,
            "-m",
            "framework.evaluate",
            f"ckpt={run / 'checkpoints' / 'final.ckpt'}",
            *OVERRIDES,
            f"record_as={SPLIT}",
            f"out_dir={run / 'eval_true_poses'}",
        ]
        done = subprocess.run(cmd, capture_output=True, text=True)
        status = "ok" if done.returncode == 0 else f"failed: {done.stderr.strip().splitlines()[-1:]}"
        print(f"[{i}/{len(runs)}] {run.name}: {status}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Sweeps run through real Hydra launchers: a two-job multirun on a local Ray instance and through submitit_local.

The jobs are a tiny static fit (few steps, small images) so the test measures the launchers, not training. Each
launcher must leave both jobs' checkpoints on disk and no process of its own behind.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module

TINY_JOB = [
    "+experiment=static_fit",
    "trainer.max_steps=2",
    "data.resolution=32",
    "data.num_train_views=4",
    "data.num_test_views=2",
    "gaussians.num=300",
    "logger=none",
    "eval.after_fit=false",
    "seed=0,1",
]


def _own_processes(names: tuple[str, ...]) -> list[str]:
    """Command lines of running processes whose command line mentions one of `names` (Ray's daemons, workers)."""
    out = subprocess.run(["ps", "-eo", "pid=,args="], capture_output=True, text=True, check=True).stdout
    return [line for line in out.splitlines() if any(n in line for n in names) and "ps -eo" not in line]


def _run_sweep(tmp_path: Path, launcher: list[str]) -> list[Path]:
    env = {**os.environ, "HYDRA_FULL_ERROR": "1"}
    cmd = [sys.executable, "-m", "framework.train", "-m", *launcher, *TINY_JOB, f"paths.root={tmp_path}"]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return sorted(tmp_path.glob("multirun/*/*/checkpoints/last.ckpt"))


def _require(module: str) -> None:
    if importlib.util.find_spec(module) is None:
        pytest.fail(f"{module} is not installed: install the `launchers` extra (pip install -e '.[launchers]')")


@pytest.mark.slow
def test_submitit_local_runs_both_jobs(tmp_path: Path) -> None:
    _require("hydra_plugins.hydra_submitit_launcher")
    ckpts = _run_sweep(tmp_path, ["hydra/launcher=submitit_local"])
    assert [p.parents[1].name.split("seed=")[-1] for p in ckpts] == ["0", "1"]
    assert len(list(tmp_path.glob("multirun/*/.submitit/*/*_result.pkl"))) == 2


@pytest.mark.slow
def test_ray_local_runs_both_jobs_and_leaves_no_process(tmp_path: Path) -> None:
    _require("hydra_plugins.hydra_ray_launcher")
    daemons = ("raylet", "gcs_server", "ray::", "ray/dashboard", "default_worker.py")
    before = set(_own_processes(daemons))
    ckpts = _run_sweep(
        tmp_path,
        [
            "hydra/launcher=ray",
            "+hydra.launcher.ray.init.num_cpus=2",
            "+hydra.launcher.ray.init.include_dashboard=false",
        ],
    )
    assert [p.parents[1].name.split("seed=")[-1] for p in ckpts] == ["0", "1"]
    left = [p for p in _own_processes(daemons) if p not in before]
    assert not left, f"the Ray launcher left processes behind: {left}"


def test_slurm_launcher_config_composes() -> None:
    """The cluster form cannot run here; its config must compose with our sweep and keep our run layout."""
    _require("hydra_plugins.hydra_submitit_launcher")
    with initialize_config_module("framework.conf", version_base="1.3"):
        cfg = compose(
            "ablations",
            overrides=[
                "hydra/launcher=submitit_slurm",
                "hydra.launcher.partition=gpu",
                "hydra.launcher.gpus_per_node=1",
            ],
            return_hydra_config=True,
        )
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("SlurmLauncher")
    assert launcher.partition == "gpu" and launcher.gpus_per_node == 1
    assert cfg.hydra.sweep.dir.startswith("${paths.root}/ablations/") or "ablations" in str(cfg.hydra.sweep.dir)

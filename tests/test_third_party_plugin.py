"""A third-party plugin, for real: pip-install the example package from tests/fixtures and train with it.

The package is installed with `pip install --target` into a temporary folder put on PYTHONPATH (no network: no
dependencies, no build isolation, no index). That is the cheapest install that still goes through pip, a wheel build
and the distribution metadata that entry-point discovery reads; a temporary venv with --system-site-packages
needs its own setuptools + wheel to build, which an offline machine may not have. Nothing in this repository is
touched: the fixture is copied first (building writes build/ and *.egg-info next to the sources), and runs write
their outputs under the temporary folder.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

FIXTURE = Path(__file__).parent / "fixtures" / "splatrig_example_plugin"
DIST = "splatrig-example-plugin"


def run(args: list[str], env: dict[str, str], cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        args, env=env, cwd=cwd, capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL
    )


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, str]]:
    """(work dir, environment) with the example plugin pip-installed and importable."""
    root = tmp_path_factory.mktemp("third_party")
    src = root / "src"
    shutil.copytree(FIXTURE, src, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    site = root / "site"
    env = dict(os.environ)
    env.pop("SPLATRIG_PLUGINS", None)  # the entry points alone must find it
    proc = run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--no-deps",
            "--no-build-isolation",
            "--no-index",
            "--disable-pip-version-check",
            "--quiet",
            "--target",
            str(site),
            str(src),
        ],
        env,
        root,
    )
    assert proc.returncode == 0, f"pip install of the example plugin failed:\n{proc.stdout}\n{proc.stderr}"
    env["PYTHONPATH"] = os.pathsep.join([str(site), *filter(None, [env.get("PYTHONPATH")])])
    return root, env


def test_installed_plugin_is_listed_with_its_distribution(installed: tuple[Path, dict[str, str]]) -> None:
    root, env = installed
    proc = run([sys.executable, "-m", "framework.plugins"], env, root)
    assert proc.returncode == 0, proc.stderr
    rows = [
        [c.strip() for c in line.strip().strip("|").split("|")]
        for line in proc.stdout.splitlines()
        if line.startswith("|")
    ]
    assert ["densifier", "example_prune_only", DIST, "available"] in rows, proc.stdout
    assert "Plugins that failed to import" not in proc.stdout
    assert "Config search paths added by plugins: pkg://splatrig_example_plugin.conf" in proc.stdout


def test_training_with_the_plugin_selected_on_the_command_line(installed: tuple[Path, dict[str, str]]) -> None:
    """A short static_fit run with `densifier=example_prune_only`; the plugin must really prune.

    All Gaussians start at the same opacity; after a few Adam steps some have moved below it and some above, so
    pruning at min_opacity = the initial opacity removes some but never all of them.
    """
    root, env = installed
    run_dir = root / "run"
    steps, num = 4, 1000
    overrides = (
        f"+experiment=static_fit densifier=example_prune_only trainer.max_steps={steps} trainer.val_every=1000 "
        f"callbacks.checkpoint_every={steps} densifier.start=2 densifier.every=2 densifier.min_opacity=0.1 "
        f"gaussians.opacity=0.1 gaussians.num={num} eval.after_fit=false hydra.run.dir={run_dir}"
    ).split()
    proc = run([sys.executable, "-m", "framework.train", *overrides], env, root, timeout=600)
    assert proc.returncode == 0, f"training failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-8000:]}"
    cfg = yaml.safe_load((run_dir / "config_resolved.yaml").read_text())
    assert cfg["densifier"] == {
        "name": "example_prune_only",
        "every": 2,
        "start": 2,
        "stop": 1_000_000_000,
        "min_opacity": 0.1,
    }
    ckpt = torch.load(run_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert ckpt["global_step"] == steps
    means = [v for k, v in ckpt["state_dict"].items() if k.endswith("means")]
    assert len(means) == 1, list(ckpt["state_dict"])
    n_final = means[0].shape[0]
    pruned = ckpt["densifier_state"]["n_pruned"]
    assert 0 < pruned < num and n_final == num - pruned

"""End-to-end training through the real entry point: a tiny static fit, interruption and resume, bad input."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

TINY = [
    "+experiment=static_fit",
    "data.resolution=32",
    "data.num_train_views=6",
    "data.num_test_views=2",
    "data.supersample=1",
    "gaussians.num=400",
    "densifier.refine_start=5",
    "densifier.refine_every=10",
    "densifier.grad_threshold=1e-7",
    "trainer.val_every=20",
    "callbacks.checkpoint_every=10",
    "callbacks.image_every=20",
    "callbacks.progress_bar=false",
    "eval.metrics=[psnr,ssim]",
    "threads=1",
]


HELPERS = Path(__file__).resolve().parent / "helpers"


def _train(
    tmp_path: Path, *overrides: str, wait: bool = True, cache: Path | None = None, faults: dict[str, str] | None = None
) -> subprocess.Popen | subprocess.CompletedProcess:
    """Run `python -m framework.train` on the tiny static fit; `faults` (env values) loads tests/helpers/faults.py."""
    env = dict(os.environ, SPLATRIG_CACHE_DIR=str(cache or tmp_path / "cache"), PYTHONUNBUFFERED="1")
    if faults is not None:
        path = os.pathsep.join([str(HELPERS), env.get("PYTHONPATH", "")])
        env.update(faults, SPLATRIG_PLUGINS="faults", PYTHONPATH=path)
    cmd = [sys.executable, "-m", "framework.train", *TINY, f"paths.root={tmp_path / 'out'}", *overrides]
    if wait:
        return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path)


def _run_dirs(tmp_path: Path) -> list[Path]:
    return sorted((tmp_path / "out" / "static_fit").glob("*"))


def _load(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)


def test_static_fit_trains_and_reports(tmp_path: Path):
    proc = _train(tmp_path, "trainer.max_steps=40")
    assert proc.returncode == 0, proc.stderr[-3000:]
    run = _run_dirs(tmp_path)[-1]
    assert (run / "config_resolved.yaml").is_file()
    assert (run / "checkpoints" / "last.ckpt").is_file()
    assert (run / "checkpoints" / "best.ckpt").is_file()
    summary = (run / "eval" / "summary.md").read_text()
    assert "novel_view" in summary and "psnr" in summary
    assert str(run) in proc.stdout  # tells the user where the results are
    ckpt = _load(run / "checkpoints" / "last.ckpt")
    assert ckpt["global_step"] == 40
    events = list((run / "tb").rglob("events.out.tfevents.*"))
    assert events, "no TensorBoard event file written"


def test_interrupted_run_resumes_with_step_count_and_optimizer_state(tmp_path: Path):
    proc = _train(tmp_path, "trainer.max_steps=200", wait=False)
    ckpt_path = None
    deadline = time.time() + 300
    try:
        while time.time() < deadline:
            runs = _run_dirs(tmp_path)
            candidate = runs[-1] / "checkpoints" / "last.ckpt" if runs else None
            if candidate is not None and candidate.is_file():
                time.sleep(0.5)  # let the write finish
                try:
                    step = _load(candidate)["global_step"]
                except Exception:
                    continue
                if step >= 30:
                    ckpt_path = candidate
                    break
            if proc.poll() is not None:
                pytest.fail(f"training ended before it could be interrupted:\n{proc.stdout.read()[-3000:]}")
            time.sleep(0.2)
        assert ckpt_path is not None, "no checkpoint at step >= 30 appeared"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    saved = _load(ckpt_path)
    step0 = saved["global_step"]
    assert step0 < 200
    n0 = saved["state_dict"]["avatar.gaussians.params.means"].shape[0]
    assert n0 != 400, "densification did not change N before the interruption; the resize path is untested"

    final_steps = step0 + 30
    proc = _train(tmp_path, f"trainer.max_steps={final_steps}", f"ckpt_path={ckpt_path}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    resumed = _run_dirs(tmp_path)[-1] / "checkpoints" / "last.ckpt"
    final = _load(resumed)
    assert final["global_step"] == final_steps
    opt = final["optimizer_states"][0]
    names = [g["name"] for g in opt["param_groups"]]
    means_state = opt["state"][opt["param_groups"][names.index("means")]["params"][0]]
    # Adam's per-parameter step counter continued from the interrupted run rather than restarting at 0.
    assert int(means_state["step"]) > final_steps - step0
    n = final["state_dict"]["avatar.gaussians.params.means"].shape[0]
    assert means_state["exp_avg"].shape[0] == n


def test_unknown_component_gives_one_clear_message(tmp_path: Path):
    proc = _train(tmp_path, "trainer.max_steps=1", "rasterizer.name=torch_reff")
    assert proc.returncode == 2
    assert "unknown rasterizer 'torch_reff'" in proc.stderr
    assert "Did you mean 'torch_ref'" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_missing_config_option_names_the_group(tmp_path: Path):
    proc = _train(tmp_path, "rasterizer=does_not_exist")
    assert proc.returncode != 0
    assert "rasterizer/does_not_exist" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_checkpoint_from_incompatible_config_is_refused(tmp_path: Path):
    proc = _train(tmp_path, "trainer.max_steps=10")
    assert proc.returncode == 0, proc.stderr[-3000:]
    ckpt = _run_dirs(tmp_path)[-1] / "checkpoints" / "last.ckpt"
    proc = _train(tmp_path, "trainer.max_steps=20", f"ckpt_path={ckpt}", "corrector=latent")
    assert proc.returncode == 2
    assert "incompatible config" in proc.stderr and "corrector" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_paper_full_fast_dev_run_on_cpu(tmp_path: Path):
    """The paper's model end to end (studio generation, body, corrector, residual deformer, losses, densifier) for one
    step, on the procedural body so the test needs no Anny cache."""
    env = dict(os.environ, SPLATRIG_CACHE_DIR=str(tmp_path / "cache"), PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "framework.train", "+experiment=paper_full", "trainer.fast_dev_run=true",
           "body=procedural", "data.body=procedural", "data.resolution=32", "data.views=4", "data.frames=4",
           "data.supersample=1", "deformer.grid_resolution=12", "gaussians.num=300", "stages.stage1_steps=0",
           "callbacks.progress_bar=false", f"paths.root={tmp_path / 'out'}", "threads=1"]  # fmt: skip
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "profile=cpu" in proc.stderr
    assert "results:" in proc.stdout


def test_standalone_evaluation_reproduces_the_end_of_training_metrics(tmp_path: Path):
    """`python -m framework.evaluate ckpt=...` must render the model as training left it (e.g. its SH degree,
    which follows the step count), so its table equals the one printed at the end of training."""
    proc = _train(tmp_path, "trainer.max_steps=40", "gaussians.sh_increase_every=10")
    assert proc.returncode == 0, proc.stderr[-3000:]
    run = _run_dirs(tmp_path)[-1]
    env = dict(os.environ, SPLATRIG_CACHE_DIR=str(tmp_path / "cache"))
    out = tmp_path / "standalone"
    cmd = [sys.executable, "-m", "framework.evaluate", f"ckpt={run / 'checkpoints' / 'last.ckpt'}",
           "metrics=[psnr,ssim]", f"out_dir={out}"]  # fmt: skip
    ev = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert ev.returncode == 0, ev.stderr[-3000:]
    assert (out / "summary.md").read_text() == (run / "eval" / "summary.md").read_text()

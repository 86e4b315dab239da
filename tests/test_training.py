"""End-to-end training through the real entry point: a tiny static fit, interruption and resume, bad input."""

from __future__ import annotations

import json
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
    tmp_path.mkdir(parents=True, exist_ok=True)  # the run's working directory
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


@pytest.fixture(scope="module")
def whole_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, subprocess.CompletedProcess]:
    """One uninterrupted tiny static fit of 60 steps (the reference of the kill/resume test too)."""
    root = tmp_path_factory.mktemp("whole")
    proc = _train(root, "trainer.max_steps=60", cache=root / "cache")
    assert proc.returncode == 0, proc.stderr[-3000:]
    return root, proc


def test_static_fit_trains_and_reports(whole_run):
    root, proc = whole_run
    run = _run_dirs(root)[-1]
    assert (run / "config_resolved.yaml").is_file()
    assert (run / "checkpoints" / "last.ckpt").is_file()
    assert not (run / "checkpoints" / "best.ckpt").exists(), "no checkpoint may be selected on a test split"
    summary = (run / "eval" / "summary.md").read_text()
    assert "novel_view" in summary and "psnr" in summary
    assert str(run) in proc.stdout  # tells the user where the results are
    ckpt = _load(run / "checkpoints" / "last.ckpt")
    assert ckpt["global_step"] == 60
    events = list((run / "tb").rglob("events.out.tfevents.*"))
    assert events, "no TensorBoard event file written"
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    # Scalars are logged only on the steps Lightning writes (log_every = 25 by default): steps 24 and 49 of 0..59.
    scalars = EventAccumulator(str(events[0].parent)).Reload()
    for tag in ("loss/total", "loss/l1", "train/psnr", "train/ms_per_iteration", "lr/means", "train/stage"):
        assert [e.step for e in scalars.Scalars(tag)] == [24, 49], tag


def test_a_static_fit_compacts_and_refits(whole_run, tmp_path: Path, monkeypatch):
    """`framework.prune` on a scene without a body: faint Gaussians go, the rest are refitted, the report says there
    are no skin weights (rather than "stored"), and the compact file loads and renders the test views no worse than
    a prune of the same Gaussians without the refit."""
    from framework.compaction.compact import prune_checkpoint

    root, _ = whole_run
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(root / "cache"))
    ckpt = _run_dirs(root)[-1] / "checkpoints" / "last.ckpt"
    kw = dict(measure=True, repeats=0, device="cpu", prune_tolerance=0.03)
    plain = prune_checkpoint(ckpt, tmp_path / "plain.ckpt", refit_steps=0, **kw)
    refit = prune_checkpoint(ckpt, tmp_path / "refit.ckpt", refit_steps=30, **kw)
    assert refit.skin_weights_stored is None and "no skin weights (no body)" in refit.summary()
    assert refit.after.num_gaussians == plain.after.num_gaussians < refit.before.num_gaussians
    assert refit.after.psnr["novel_view"] > plain.after.psnr["novel_view"]


def test_loader_processes_train_exactly_as_the_main_process(tmp_path: Path, whole_run):
    """Frames decoded by DataLoader processes (the GPU profile's `loader_workers`) arrive in the order the step
    sampler draws them, so the run ends with the same parameters, bit for bit, as the one decoding in-process."""
    whole = whole_run[0]
    proc = _train(tmp_path, "trainer.max_steps=60", "data_loader.num_workers=2", cache=whole / "cache")
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = _load(_run_dirs(tmp_path)[-1] / "checkpoints" / "last.ckpt")["state_dict"]
    want = _load(_run_dirs(whole)[-1] / "checkpoints" / "last.ckpt")["state_dict"]
    assert got.keys() == want.keys()
    assert want["avatar.gaussians.params.means"].shape[0] != 400, "the reference densified"
    for key, value in want.items():
        assert torch.equal(got[key], value), key


def test_kill_during_a_checkpoint_write_then_resume_matches_an_uninterrupted_run(tmp_path: Path, whole_run):
    """A run killed while it writes the step-30 checkpoint keeps the step-20 one loadable; resumed, it continues the
    step count, the optimizer's and the densifier's state and the random streams, and ends where an uninterrupted
    run ends (same parameters within float noise, same metrics)."""
    whole = whole_run[0]
    cache, killed = whole / "cache", tmp_path / "killed"
    killed.mkdir()
    marker = tmp_path / "stalled"
    faults = {"SPLATRIG_TEST_STALL_CHECKPOINT_AT": "30", "SPLATRIG_TEST_STALL_MARKER": str(marker)}
    proc = _train(killed, "trainer.max_steps=60", wait=False, cache=cache, faults=faults)
    try:
        deadline = time.time() + 300
        while not marker.exists():
            if proc.poll() is not None:
                pytest.fail(f"training ended before the stalled write:\n{proc.stdout.read()[-3000:]}")
            assert time.time() < deadline, "the step-30 checkpoint write never started"
            time.sleep(0.2)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    ckpt_dir = _run_dirs(killed)[-1] / "checkpoints"
    assert list(ckpt_dir.glob(".last.ckpt.tmp-*")), "the kill did not happen inside a checkpoint write"
    saved = _load(ckpt_dir / "last.ckpt")  # the previous checkpoint, complete
    assert saved["global_step"] == 20
    assert saved["state_dict"]["avatar.gaussians.params.means"].shape[0] != 400, "no densification before the kill"

    proc = _train(killed, "trainer.max_steps=60", f"ckpt={ckpt_dir / 'last.ckpt'}", cache=cache)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert len(_run_dirs(killed)) == 1  # the resumed run continued in its own folder
    assert "not resumable" not in proc.stderr  # the loader's state (seed, position) went into the checkpoint
    resumed_dir = _run_dirs(killed)[-1]
    final = _load(resumed_dir / "checkpoints" / "last.ckpt")
    reference = _load(_run_dirs(whole)[-1] / "checkpoints" / "last.ckpt")
    assert final["global_step"] == reference["global_step"] == 60
    for key, value in reference["state_dict"].items():
        assert final["state_dict"][key].shape == value.shape, key
        torch.testing.assert_close(final["state_dict"][key], value, atol=1e-5, rtol=1e-4, msg=key)
    opt, ref_opt = final["optimizer_states"][0], reference["optimizer_states"][0]
    for state, ref_state in zip(opt["state"].values(), ref_opt["state"].values(), strict=True):
        assert int(state["step"]) == int(ref_state["step"])  # Adam's counters continued, not restarted
        torch.testing.assert_close(state["exp_avg_sq"], ref_state["exp_avg_sq"], atol=1e-8, rtol=1e-3)
    for key, value in reference["densifier_state"].items():
        if isinstance(value, torch.Tensor):
            torch.testing.assert_close(final["densifier_state"][key], value, atol=1e-6, rtol=1e-4, msg=key)
    summary = (_run_dirs(whole)[-1] / "eval" / "summary.md").read_text()
    assert (resumed_dir / "eval" / "summary.md").read_text() == summary


def test_unknown_component_gives_one_clear_message(tmp_path: Path):
    proc = _train(tmp_path, "trainer.max_steps=1", "rasterizer.name=torch_reff")
    assert proc.returncode == 2
    assert "unknown rasterizer 'torch_reff'" in proc.stderr
    assert "Did you mean 'torch_ref'" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_missing_config_option_names_the_group(tmp_path: Path):
    proc = _train(tmp_path, "rasterizer=does_not_exist")
    assert proc.returncode == 2
    assert "rasterizer=does_not_exist: no such option in group 'rasterizer'" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_checkpoint_from_incompatible_config_is_refused(tmp_path: Path):
    proc = _train(tmp_path, "trainer.max_steps=10")
    assert proc.returncode == 0, proc.stderr[-3000:]
    ckpt = _run_dirs(tmp_path)[-1] / "checkpoints" / "last.ckpt"
    proc = _train(tmp_path, "trainer.max_steps=20", f"ckpt={ckpt}", "corrector=latent")
    assert proc.returncode == 2
    assert "incompatible config" in proc.stderr and "corrector" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_paper_full_fast_dev_run_on_cpu(tmp_path: Path):
    """The paper's model end to end (studio generation, body, corrector, residual deformer, losses, densifier) for one
    step, on the procedural body so the test needs no Anny cache."""
    env = dict(os.environ, SPLATRIG_CACHE_DIR=str(tmp_path / "cache"), PYTHONUNBUFFERED="1")
    cmd = [
        sys.executable,
        "-m",
        "framework.train",
        "+experiment=paper_full",
        "trainer.fast_dev_run=true",
        "body=procedural",
        "data.body=procedural",
        "data.resolution=32",
        "data.num_views=4",
        "data.num_frames=4",
        "data.supersample=1",
        "deformer.grid_resolution=12",
        "gaussians.num=300",
        "stages.stage1_steps=0",
        "callbacks.progress_bar=false",
        f"paths.root={tmp_path / 'out'}",
        "threads=1",
    ]
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
    trained = {f.name: f.stat().st_mtime_ns for f in (run / "eval").iterdir()}
    cmd = [
        sys.executable,
        "-m",
        "framework.evaluate",
        f"ckpt={run / 'checkpoints' / 'last.ckpt'}",
        "metrics=[psnr,ssim]",
    ]
    ev = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert ev.returncode == 0, ev.stderr[-3000:]
    out = run / "eval_last"  # the default folder of a checkpoint other than final.ckpt: training's own eval stays
    assert f"evaluation written to {out}" in ev.stdout
    assert {f.name: f.stat().st_mtime_ns for f in (run / "eval").iterdir()} == trained
    assert (out / "summary.md").read_text() == (run / "eval" / "summary.md").read_text()


# paper_full at toy size: procedural body, 40 px, 4 views, 6 frames (one held-out motion frame), 30 steps with stage 2
# from step 10 and the opacity-reset schedule compressed to fit (resets at 5 in stage 1 and 20 = 10 + 10 in stage 2)
PAPER_TINY = [
    "+experiment=paper_full",
    "body=procedural",
    "data.body=procedural",
    "data.resolution=40",
    "data.num_views=4",
    "data.num_frames=6",
    "data.supersample=1",
    "data.workers=1",
    "deformer.grid_resolution=12",
    "gaussians.num=300",
    "trainer.max_steps=30",
    "stages.stage1_steps=10",
    "trainer.val_every=15",
    "densifier.first_reset=5",
    "densifier.reset_every=10",
    "densifier.refine_stop=25",
    "densifier.reset_restart=10",
    "densifier.refine_start=2",
    "densifier.refine_every=5",
    "callbacks.checkpoint_every=10",
    "callbacks.image_every=0",
    "callbacks.progress_bar=false",
    "eval.metrics=[psnr,ssim]",
    "eval.fps_frames=4",
    "threads=1",
]


def test_paper_full_both_stages_bakes_weights_and_evaluates_novel_poses(tmp_path: Path, monkeypatch):
    """The whole recipe through a real trainer: stage 1, the switch to stage 2 (corrector and F_dw on, the densifier's
    reset count restarted), weight baking into final.ckpt, and the novel-view and novel-pose evaluation."""
    from framework.lightning.trained_model import load_module

    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(tmp_path / "cache"))
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "framework.train", *PAPER_TINY, f"paths.root={tmp_path / 'out'}"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "step 10: stage 2" in proc.stdout + proc.stderr
    run = sorted((tmp_path / "out" / "paper_full").glob("*"))[-1]
    ckpts = run / "checkpoints"
    assert not (ckpts / "best.ckpt").exists()
    last = _load(ckpts / "last.ckpt")
    assert last["global_step"] == 30 and last["densifier_state"]["stage2_start"] == 10
    assert last["splatrig_stage"] == {"corrector_enabled": True, "deformer_enabled": True}
    # final.ckpt carries each Gaussian's blend weights as the residual deformer computed them at the end of training
    module = load_module(ckpts / "final.ckpt")
    baked = module.avatar.gaussians.params["skin_weights"].detach()
    deformer = module.avatar.deformer
    assert deformer.enabled and baked.shape == (module.avatar.gaussians.num, 17)
    with torch.no_grad():
        live = deformer.weights(module.avatar.gaussians.params["means"])
    # the bake runs the compiled loops (float64 inside), `weights` torch in float32: w0 + F_dw (paper_full's additive
    # form) is not renormalised, so the float32 lookup's rounding stays whole (a few ulps of 1)
    torch.testing.assert_close(baked, live, atol=2e-6, rtol=0)
    trained_residual = any(p.abs().max() > 0 for p in deformer.mlp[-1].parameters())
    assert trained_residual, "F_dw never left its zero initialisation: stage 2 did not train it"
    summary = (run / "eval" / "summary.md").read_text()
    assert "novel_view" in summary and "novel_pose" in summary
    # the run's cost in results.json: render speed with baked weights (both cases timed), step time, size
    record = json.loads((run / "results.json").read_text())
    fps = record["render_fps"]
    assert fps["novel_pose"] > 0 and fps["novel_view"] > 0 and fps["split"] == "novel_pose" and fps["frames"] == 4
    # results.json rounds train_seconds to 0.01 s and seconds_per_step to 1e-4 s, both from the unrounded time
    assert record["seconds_per_step"] == pytest.approx(record["train_seconds"] / 30, abs=0.005 / 30 + 5e-5 + 1e-9)
    assert record["checkpoint"] == "final.ckpt" and record["checkpoint_bytes"] == (ckpts / "final.ckpt").stat().st_size
    learned = sum(
        t.numel() * t.element_size() for k, t in last["state_dict"].items() if not k.startswith("avatar.body.")
    )
    # the final model also holds the baked weights [N, 17] (float32) that last.ckpt, saved before baking, lacks
    assert record["model_bytes"] == learned + module.avatar.gaussians.num * 17 * 4
    assert record["num_gaussians"] == module.avatar.gaussians.num
    # the same avatar's novel-pose frames with the compiled CPU rasterizer: torch_ref's images to float32 rounding
    # (a pixel may move by one pair's weight at the 1/255 cut, tests/test_numba_rasterizer.py), timed through the
    # same interleaved path the compaction tools use
    from framework.evaluation.run_cost import distinct_frame_items, use_rasterizer
    from framework.lightning.trained_model import datamodule_for, interleaved_fps

    dm = datamodule_for(module)
    poses = dm.split("novel_pose")
    module.eval()
    sh_degree = module.sh_degree(module.trained_steps())
    with torch.no_grad():
        batches = [poses[i] for i in distinct_frame_items(poses, 2)]
        ref = [module.avatar(b, sh_degree=sh_degree).render.rgb for b in batches]
        use_rasterizer(module, "numba")  # also drops the posed cache, so the frames pose again
        got = [module.avatar(b, sh_degree=sh_degree).render.rgb for b in batches]
    assert type(module.avatar.rasterizer).registry_name == "numba"
    for a, b in zip(got, ref, strict=True):
        err = (a - b).abs()
        assert float(err.max()) <= 1.0 / 255.0 and float((err > 2e-5).float().mean()) <= 1e-3
    fps = interleaved_fps({"final": ckpts / "final.ckpt"}, warmup=1, repeats=2, rounds=1, rasterizer="numba")
    assert fps["final"][0] > 0 and fps["final"][1] > 0


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_gpu_training_resumes_rolls_back_and_evaluates_on_the_device(tmp_path: Path):
    """On CUDA: the after-fit evaluation and frame timing run on the GPU (Lightning's teardown moves the module to the
    CPU), a resumed run densifies with its restored statistics (loaded on the CPU before the module moves), and a
    rollback restores the CUDA random state (a CPU byte tensor, from a checkpoint loaded onto the GPU)."""
    first = tmp_path / "first"
    proc = _train(first, "trainer.max_steps=30")  # accelerator auto: the GPU
    assert proc.returncode == 0, proc.stderr[-3000:]
    run = _run_dirs(first)[-1]
    record = json.loads((run / "results.json").read_text())
    assert record["render_fps"]["device"].startswith("cuda"), record["render_fps"]
    proc = _train(first, "trainer.max_steps=45", f"ckpt={run / 'checkpoints' / 'last.ckpt'}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    rolled = tmp_path / "rolled"
    proc = _train(
        rolled,
        "trainer.max_steps=40",
        "divergence.action=rollback",
        "+loss.terms.fault={name: fault, weight: 1.0, at_step: 25, kind: nan_grad}",
        faults={},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert any("rolled back" in line for line in proc.stderr.splitlines()), proc.stderr[-3000:]

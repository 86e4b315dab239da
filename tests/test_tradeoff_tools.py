"""The trade-off sweep's after-training tools: `record_field` (framework.evaluation.run_record), tools/record_fps.py
(the viewer's frame rate stored in each run's results.json) and tools/compact_point.py's record of a pruned run."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest
from tool_module import load_tool

from framework.evaluation.run_record import load_run_record, record_field, record_metrics, write_run_record


def _record(run: Path, **extra) -> Path:
    return write_run_record(run, experiment="x", overrides=["+tradeoff=baseline", "seed=0"], seed=0, **extra)


def test_record_field_keeps_the_record_and_lists_the_field_once(tmp_path) -> None:
    _record(tmp_path, metrics={"novel_pose": {"image": {"psnr": 20.0}}})
    before = load_run_record(tmp_path / "results.json")
    record_field(tmp_path, "viewer_fps", {"resolution": 32})
    record_field(tmp_path, "viewer_fps", {"resolution": 64})
    after = load_run_record(tmp_path / "results.json")
    assert after["viewer_fps"] == {"resolution": 64}
    assert after["recorded_later"] == ["viewer_fps"]
    assert {k: v for k, v in after.items() if k not in ("viewer_fps", "recorded_later")} == before
    record_metrics(tmp_path, "novel_pose_true_poses", {"image": {"psnr": 21.0}})
    record_metrics(tmp_path, "novel_pose_true_poses", {"image": {"psnr": 22.0}})
    after = load_run_record(tmp_path / "results.json")
    assert after["metrics"] == {
        "novel_pose": {"image": {"psnr": 20.0}},
        "novel_pose_true_poses": {"image": {"psnr": 22.0}},
    }
    assert after["recorded_later"] == ["viewer_fps", "novel_pose_true_poses"]


def test_record_fps_times_the_runs_without_the_field(tiny_avatar, tmp_path, monkeypatch) -> None:
    ckpt, cache = tiny_avatar
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(cache))
    tool = load_tool("record_fps")
    runs = {name: tmp_path / "sweep" / name for name in ("0_new_seed0", "1_done_seed0", "2_no_ckpt_seed0")}
    for name, run in runs.items():
        (run / "checkpoints").mkdir(parents=True)
        if name != "2_no_ckpt_seed0":
            shutil.copy(ckpt, run / "checkpoints" / "final.ckpt")
        _record(run, checkpoint="final.ckpt")
    done = {"resolution": 512, "paths": {}}
    record_field(runs["1_done_seed0"], "viewer_fps", done)
    assert [r for r, _ in tool.pending([tmp_path / "sweep"])] == [runs["0_new_seed0"]]
    assert tool.main([str(tmp_path / "sweep"), "--resolution", "32", "--warmup", "1", "--repeats", "2"]) == 0

    fps = load_run_record(runs["0_new_seed0"] / "results.json")["viewer_fps"]
    assert (fps["resolution"], fps["device"], fps["warmup"], fps["frames"]) == (32, "cpu", 1, 2)
    assert fps["num_gaussians"] > 0 and fps["sh_degree"] >= 0
    assert set(fps["paths"]) == {"compiled", "torch"}
    for path in fps["paths"].values():
        for case in ("novel_pose", "novel_view"):
            assert isinstance(path[case], float) and math.isfinite(path[case]) and path[case] > 0
    assert load_run_record(runs["1_done_seed0"] / "results.json")["viewer_fps"] == done
    assert "viewer_fps" not in load_run_record(runs["2_no_ckpt_seed0"] / "results.json")
    assert tool.pending([tmp_path / "sweep"]) == []  # a second call has nothing left to do


PARENT = {
    "schema": "splatrig.run/1",
    "experiment": "tradeoff_scene_auto",
    "config_name": "tradeoff",
    "overrides": ["+tradeoff=scene_auto", "seed=1", "data=synthetic_studio_realistic", "profile=ablation"],
    "seed": 1,
    "profile": "ablation",
    "data": "synthetic_studio",
    "steps": 4000,
    "max_steps": 4000,
    "train_seconds": 500.0,
    "train_cpu_seconds": 700.0,
    "run_seconds": 520.0,
    "num_gaussians": 10000,
    "peak_rss_mib": 900.0,
    "cuda_peak_mib": None,
    "seconds_per_step": 0.125,
    "stage_seconds": {"stage1": {"steps": 1000, "seconds": 100.0, "steps_per_second": 10.0}},
    "render_fps": {"novel_pose": 40.0, "novel_view": 120.0},
    "model_bytes": 4000000,
    "checkpoint_bytes": 12000000,
    "checkpoint": "final.ckpt",
    "metrics": {"novel_pose": {"image": {"psnr": 26.0}}, "novel_pose_true_poses": {"image": {"psnr": 29.0}}},
    "code": {"version": "0.1.0", "commit": "abc"},
    "created": "2026-01-01T00:00:00+00:00",
    "recorded_later": ["novel_pose_true_poses", "viewer_fps"],
    "viewer_fps": {"resolution": 512},
}


def test_compact_record_charges_the_prune_to_training() -> None:
    tool = load_tool("compact_point")
    prune = tool.Measured(returncode=0, seconds=60.004, cpu_seconds=90.0, peak_rss_mib=1200.04)
    model = {"num_gaussians": 6000, "model_bytes": 2000000, "checkpoint": "final.ckpt", "checkpoint_bytes": 2100000}
    metrics = {"novel_view": {"image": {"psnr": 28.5}}, "novel_pose": {"image": {"psnr": 25.8}}}
    parent = json.loads(json.dumps(PARENT))
    fields = tool.compact_record(parent, "17_scene_auto_seed1", "scene_auto", prune, 30.0, model, metrics, 1500)
    assert parent == PARENT  # the parent's record is not changed
    assert fields == {
        "experiment": "tradeoff_scene_auto_compact",
        "config_name": "tradeoff",
        "overrides": ["+tradeoff=scene_auto_compact", "seed=1", "data=synthetic_studio_realistic", "profile=ablation"],
        "seed": 1,
        "profile": "ablation",
        "data": "synthetic_studio",
        "steps": 4000,
        "max_steps": 4000,
        "train_seconds": 560.0,
        "train_cpu_seconds": 790.0,
        "run_seconds": 610.0,
        "num_gaussians": 6000,
        "peak_rss_mib": 1200.0,
        "cuda_peak_mib": None,
        "stage_seconds": {"stage1": {"steps": 1000, "seconds": 100.0, "steps_per_second": 10.0}},
        "model_bytes": 2000000,
        "checkpoint_bytes": 2100000,
        "checkpoint": "final.ckpt",
        "metrics": metrics,
        "derived_from": {
            "run": "17_scene_auto_seed1",
            "step": "framework.prune",
            "prune_seconds": 60.0,
            "prune_cpu_seconds": 90.0,
            "prune_peak_rss_mib": 1200.0,
            "refit_steps": 1500,
        },
    }
    smaller = tool.Measured(returncode=0, seconds=10.0, cpu_seconds=10.0, peak_rss_mib=500.0)
    no_cpu = {k: v for k, v in PARENT.items() if k != "train_cpu_seconds"}
    fields = tool.compact_record(no_cpu, "p", "scene_auto", smaller, 0.0, model, metrics, 0)
    assert fields["peak_rss_mib"] == 900.0 and fields["train_cpu_seconds"] is None
    with pytest.raises(ValueError, match=r"\+tradeoff=baseline"):
        tool.compact_record(PARENT, "p", "baseline", prune, 0.0, model, metrics, 0)


def test_compact_point_finds_the_points_runs_not_yet_compacted(tmp_path) -> None:
    tool = load_tool("compact_point")
    sweep = tmp_path / "sweep"
    for name, point, seed in (("0_scene_auto_seed0", "scene_auto", 0), ("1_scene_auto_seed1", "scene_auto", 1)):
        run = sweep / name
        (run / "checkpoints").mkdir(parents=True)
        (run / "checkpoints" / "final.ckpt").write_bytes(b"")
        write_run_record(run, experiment="e", overrides=[f"+tradeoff={point}", f"seed={seed}"], seed=seed)
    (sweep / "2_baseline_seed0" / "checkpoints").mkdir(parents=True)
    (sweep / "2_baseline_seed0" / "checkpoints" / "final.ckpt").write_bytes(b"")
    write_run_record(sweep / "2_baseline_seed0", experiment="b", overrides=["+tradeoff=baseline"], seed=0)
    write_run_record(sweep / "scene_auto_compact_seed1", experiment="c", overrides=[], seed=1)
    found = [run.name for run, _ in tool.pending([sweep], "scene_auto")]
    assert found == ["0_scene_auto_seed0"]

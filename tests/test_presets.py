"""The presets (`+preset=NAME`, conf/preset/): each is a measured trade-off point; it trains, composes with every
hardware profile and with `+scene=auto`, and the numbers in its header are the published table's."""

from __future__ import annotations

import csv
import os
import re
import subprocess
import sys
from importlib import resources
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from framework.reporting.tradeoff import presets_by_point

ROOT = Path(__file__).resolve().parents[1]
TABLE = ROOT / "docs" / "results" / "tradeoff_cpu" / "tradeoff.csv"
PRESETS = sorted(p.name[:-5] for p in (resources.files("framework.conf") / "preset").iterdir() if p.suffix == ".yaml")
PROFILES = sorted(p.name[:-5] for p in (resources.files("framework.conf") / "profile").iterdir() if p.suffix == ".yaml")
POINT_OF = {preset: point for point, preset in presets_by_point().items()}
# "#   training 3.1 min · 45 fps novel pose at 512² · 2.1 MB · -1.20 ± 0.10 dB novel-pose PSNR against paper_full"
HEADER = re.compile(
    r"training (?P<train_min>[\d.]+) min · (?P<fps>[\d.]+) fps .*· (?P<model_mb>[\d.]+) MB · "
    r"(?P<delta>[-+−][\d.]+) ± [\d.]+ dB"
)


def _job(overrides: list[str]) -> dict:
    with initialize_config_module(config_module="framework.conf", version_base="1.3"):
        cfg = compose(config_name="train", overrides=overrides)
    job = OmegaConf.to_container(cfg, resolve=False)
    job.pop("task_name")
    job["paths"].pop("output_dir", None)
    return job


def test_there_are_presets_and_each_wraps_one_tradeoff_point():
    assert {"fast", "balanced", "quality", "realtime"} <= set(PRESETS)
    assert set(POINT_OF) == set(PRESETS), "each preset's defaults name exactly one /tradeoff/<point>"


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("preset", PRESETS)
def test_a_preset_is_its_point_under_every_profile_and_composes_with_scene_auto(preset: str, profile: str):
    """Sizes and schedules are the profile's scaled, so a preset means the same trade on any hardware profile."""
    point = POINT_OF[preset]
    assert _job([f"profile={profile}", f"+preset={preset}"]) == _job([f"profile={profile}", f"+tradeoff={point}"])
    auto = _job([f"profile={profile}", f"+preset={preset}", "+scene=auto"])
    assert auto["scene"]["auto"] and auto["scene"]["survey"]


def _table_rows() -> dict[str, dict[str, str]]:
    with TABLE.open() as f:
        return {row["point"]: row for row in csv.DictReader(f)}


@pytest.mark.parametrize("preset", PRESETS)
def test_the_header_numbers_are_the_tables(preset: str):
    """The numbers a user reads in conf/preset/<name>.yaml are the trade-off table's, rounded as written."""
    text = (resources.files("framework.conf") / "preset" / f"{preset}.yaml").read_text()
    m = HEADER.search(text)
    assert m, f"conf/preset/{preset}.yaml: no measured-numbers line in its header"
    rows = _table_rows()
    row, base = rows[POINT_OF[preset]], rows["baseline"]
    written = {k: float(v.replace("−", "-")) for k, v in m.groupdict().items()}
    for key in ("train_min", "fps", "model_mb"):
        digits = len(m.group(key).partition(".")[2])
        assert written[key] == round(float(row[key]), digits), f"{preset}: {key}"
    delta = float(row["psnr"]) - float(base["psnr"])
    assert written["delta"] == pytest.approx(delta, abs=0.006), f"{preset}: Δ dB against paper_full"


@pytest.mark.parametrize("preset", PRESETS)
def test_a_preset_trains_a_few_steps(preset: str, tmp_path: Path):
    """Every milestone of a preset is a fraction of profile.max_steps, so a 12-step run crosses the stage switch."""
    env = dict(os.environ, SPLATRIG_CACHE_DIR=str(tmp_path / "cache"), PYTHONUNBUFFERED="1")
    cmd = [
        sys.executable,
        "-m",
        "framework.train",
        f"+preset={preset}",
        "profile=cpu",
        "profile.max_steps=12",
        "profile.resolution=32",
        "profile.num_views=4",
        "profile.num_frames=4",
        "profile.num_gaussians=300",
        "profile.max_gaussians=600",
        "body=procedural",
        "data.body=procedural",
        "data.supersample=1",
        "deformer.grid_resolution=12",
        "callbacks.progress_bar=false",
        "callbacks.image_every=0",
        "eval.metrics=[psnr]",
        "eval.fps_frames=0",
        f"paths.root={tmp_path / 'out'}",
        "threads=1",
    ]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "results:" in proc.stdout

"""The trade-off sweep and its report: Pareto fronts against a brute-force dominance check, budget recommendations
and speed per dB on runs whose answers are known by construction, the report end to end on written results.json,
and every sweep point composing to paper_full with exactly its knob changed (CPU and GPU profiles)."""

from __future__ import annotations

import csv
import functools
import io
import math
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from hydra.core.override_parser.overrides_parser import OverridesParser
from hypothesis import given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf

from framework.errors import SplatrigError
from framework.evaluation.run_record import metrics_from_summary, write_run_record
from framework.report import report
from framework.reporting.pareto import pareto_front
from framework.reporting.runs import ReportError, find_runs
from framework.reporting.tradeoff import build_points, knob_gains, parse_budget, recommend
from tests.helpers.config_keys import flat

CONF = Path(__file__).resolve().parents[1] / "conf"


# ------------------------------------------------------------------------------------------------ Pareto front
def brute_force_front(points: list[tuple[float, ...]], maximise: list[bool]) -> list[bool]:
    """O(n^2): a point is on the front unless some other point is no worse everywhere and strictly better somewhere."""

    def better_or_equal(a: float, b: float, up: bool) -> bool:
        return a >= b if up else a <= b

    def strictly_better(a: float, b: float, up: bool) -> bool:
        return a > b if up else a < b

    out = []
    for p in points:
        dominated = any(
            all(better_or_equal(q[k], p[k], maximise[k]) for k in range(len(p)))
            and any(strictly_better(q[k], p[k], maximise[k]) for k in range(len(p)))
            for q in points
        )
        out.append(not dominated)
    return out


@settings(max_examples=300, deadline=None)
@given(
    st.integers(1, 4).flatmap(
        lambda d: st.tuples(
            st.lists(st.lists(st.integers(0, 4), min_size=d, max_size=d), min_size=0, max_size=25),  # ties are common
            st.lists(st.booleans(), min_size=d, max_size=d),
        )
    )
)
def test_pareto_front_matches_brute_force(data) -> None:
    points, maximise = data
    points = [tuple(float(v) for v in p) for p in points]
    assert pareto_front(points, maximise) == brute_force_front(points, maximise)


def test_pareto_front_ties_and_missing_values() -> None:
    pts = [(1.0, 1.0), (1.0, 1.0), (0.0, 2.0), (0.5, 0.5), (math.nan, 9.0)]
    # the two equal points do not dominate each other; (0.5, 0.5) is dominated by (1, 1); NaN is never on the front
    assert pareto_front(pts, [True, True]) == [True, True, True, False, False]
    assert pareto_front(pts, [True, False]) == [True, True, False, True, False]


# ------------------------------------------------------------------------------------------------ synthetic runs
# point -> (novel-pose PSNR, render fps, training seconds, peak RSS MiB, model bytes)
POINTS = {
    "baseline": (30.0, 10.0, 600.0, 2000.0, 8_000_000),
    "sh0": (29.5, 20.0, 300.0, 1500.0, 2_000_000),  # 1 doubling of each: 2 doublings for 0.5 dB -> 4 per dB
    "gaussians_half": (29.0, 20.0, 600.0, 1500.0, 4_000_000),  # 1 doubling for 1 dB -> 1 per dB
    "fdw_off": (30.0, 10.0, 300.0, 2000.0, 8_000_000),  # 1 doubling, nothing lost: "free"
    "corrector_wide": (30.5, 5.0, 1200.0, 2500.0, 16_000_000),  # slower and better: no speed gain
    "preset_realtime": (27.0, 80.0, 150.0, 1000.0, 1_000_000),  # presets are not single knobs
}


def _write_point(root: Path, name: str, seed: int, shift: float = 0.0) -> None:
    psnr, fps, seconds, rss, size = POINTS[name]
    run = root / f"{name}_seed{seed}"
    summary = {"novel_pose/psnr": psnr + shift, "novel_view/psnr": psnr + 1}
    write_run_record(
        run,
        experiment=f"tradeoff_{name}",
        config_name="tradeoff",
        overrides=[
            f"+tradeoff={name}",
            f"seed={seed}",
            "data=synthetic_studio_realistic",
            "profile=ablation",
            "threads=1",
        ],
        seed=seed,
        profile="ablation",
        data="synthetic_studio",
        steps=1000,
        max_steps=1000,
        train_seconds=seconds,
        run_seconds=seconds,
        num_gaussians=size // 1000,
        peak_rss_mib=rss,
        cuda_peak_mib=None,
        seconds_per_step=seconds / 1000,
        render_fps={
            "novel_pose": fps,
            "novel_view": 3 * fps,
            "split": "novel_pose",
            "frames": 20,
            "warmup": 3,
            "device": "cpu",
        },
        model_bytes=size,
        checkpoint_bytes=3 * size,
        checkpoint="final.ckpt",
        metrics=metrics_from_summary(summary),
    )


@pytest.fixture()
def sweep(tmp_path: Path) -> Path:
    for name in POINTS:
        _write_point(tmp_path / "part1", name, 0, shift=0.1)
        _write_point(tmp_path / "part2", name, 1, shift=-0.1)  # seeds average to the table's PSNR
    return tmp_path


def test_points_are_means_over_seeds_and_the_front_comes_first(sweep: Path) -> None:
    points = build_points(find_runs([sweep / "part1", sweep / "part2"]))
    by = {p.label: p for p in points}
    assert set(by) == set(POINTS)
    assert by["sh0"].psnr == pytest.approx(29.5) and by["sh0"].seeds == (0, 1)
    assert by["sh0"].train_min == pytest.approx(5.0) and by["sh0"].model_mb == pytest.approx(2.0)
    # sh0 dominates gaussians_half on every objective, fdw_off dominates the baseline (equal but training time)
    assert [p.label for p in points] == [
        "corrector_wide",
        "fdw_off",
        "sh0",
        "preset_realtime",
        "baseline",
        "gaussians_half",
    ]
    assert [p.on_front for p in points] == [True, True, True, True, False, False]
    # the plane fronts: (PSNR, fps) has baseline and fdw_off tied, so both on it; (PSNR, time) has fdw_off only
    assert by["fdw_off"].front["fps"] and by["baseline"].front["fps"] and not by["gaussians_half"].front["fps"]
    assert by["fdw_off"].front["train_min"] and not by["baseline"].front["train_min"]


def test_budget_recommendations_known_by_construction(sweep: Path) -> None:
    points = build_points(find_runs([sweep]))
    assert recommend(points, parse_budget("fps>=20")).label == "sh0"  # 29.5 beats gaussians_half and the preset
    assert recommend(points, parse_budget("train_min<=5")).label == "fdw_off"  # 30.0 in 5 min
    assert recommend(points, parse_budget("model_mb <= 1.5")).label == "preset_realtime"
    assert recommend(points, parse_budget("fps>=1000")) is None
    assert recommend(points, parse_budget("psnr>=30.2")).label == "corrector_wide"
    for bad in ("fps>60", "speed>=3", "fps>=fast"):
        with pytest.raises(ReportError, match="budget"):
            parse_budget(bad)


def test_speed_per_db_ranks_the_knobs(sweep: Path) -> None:
    gains = knob_gains(build_points(find_runs([sweep])))
    assert [g.label for g in gains] == ["fdw_off", "sh0", "gaussians_half", "corrector_wide"]
    by = {g.label: g for g in gains}
    assert math.isinf(by["fdw_off"].per_db) and by["fdw_off"].train_speedup == pytest.approx(2.0)
    assert by["sh0"].per_db == pytest.approx(4.0) and by["sh0"].db_lost == pytest.approx(0.5)
    assert by["gaussians_half"].per_db == pytest.approx(1.0)
    assert by["corrector_wide"].doublings == pytest.approx(-2.0)


def test_report_end_to_end(sweep: Path, capsys) -> None:
    out = sweep / "report"
    written = report([sweep / "part1", sweep / "part2"], kind="tradeoff", out=out, budgets=["fps>=20", "model_mb<=0.5"])
    assert {p.name for p in written} >= {"tradeoff.md", "tradeoff.csv"}
    for name in (
        "tradeoff.md",
        "tradeoff.csv",
        "tradeoff_fps.png",
        "tradeoff_train_time.png",
        "tradeoff_memory.png",
        "tradeoff_model_size.png",
    ):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert any((out / "tb").rglob("events.out.tfevents.*"))
    markdown = (out / "tradeoff.md").read_text()
    assert "`fps>=20`: **sh0**" in markdown and "`model_mb<=0.5`: none meets it" in markdown
    assert markdown == capsys.readouterr().out.rstrip("\n") + "\n"
    rows = list(csv.DictReader(io.StringIO((out / "tradeoff.csv").read_text())))
    fronts = [int(r["on_front"]) for r in rows]
    assert fronts == sorted(fronts, reverse=True) and fronts.count(0) == 2
    table_order = [line.split("|")[1].strip() for line in markdown.splitlines() if line.startswith("| ")][1:7]
    assert table_order == [r["point"] for r in rows]


def test_budget_flag_belongs_to_the_tradeoff_report(sweep: Path) -> None:
    with pytest.raises(SplatrigError, match="kind=tradeoff only"):
        report([sweep], kind="table4", budgets=["fps>=1"])


# ------------------------------------------------------------------------------------------------ the sweep
#: every milestone of the schedule (each a fraction of the run's length, conf/profile/*.yaml), and the length
SCHEDULE = {
    "trainer.max_steps",
    "trainer.val_every",
    "stages.stage1_steps",
    "gaussians.sh_increase_every",
    "densifier.refine_start",
    "densifier.refine_stop",
    "densifier.refine_every",
    "densifier.first_reset",
    "densifier.reset_every",
    "densifier.reset_restart",
}
BUDGET = {"gaussians.num", "densifier.max_gaussians"}
#: point -> the config keys (or "group." prefixes) it may change relative to the baseline, and must change
KNOBS = {
    "gaussians_quarter": BUDGET,
    "gaussians_half": BUDGET,
    "gaussians_double": BUDGET,
    "sh0": {"gaussians.sh_degree"},
    "sh1": {"gaussians.sh_degree"},
    "sh2": {"gaussians.sh_degree"},
    "corrector_narrow": {"corrector.hidden"},
    "corrector_shallow": {"corrector.layers"},
    "corrector_off": {"corrector."},
    "fdw_off": {"deformer."},
    "raster_jax": {"rasterizer."},
    "raster_gsplat": {"rasterizer."},
    "resolution_half": {"data.split_overrides."},
    "steps_half": SCHEDULE,
    "preset_realtime": {"corrector.", "gaussians.sh_degree", *BUDGET},
    "preset_small": {"gaussians.sh_degree", *BUDGET},
    "preset_quick": {"deformer.", "data.split_overrides.", *SCHEDULE},
    "scene_auto": {"scene."},  # the choices themselves are made at run time, from the survey
}


@functools.cache
def _compose(point: str, profile: str):
    with initialize_config_module("framework.conf", version_base="1.3"):
        return compose(
            "tradeoff", overrides=[f"+tradeoff={point}", f"profile={profile}", "data=synthetic_studio_realistic"]
        )


def test_sweep_lists_every_cpu_point() -> None:
    with initialize_config_module("framework.conf", version_base="1.3"):
        cfg = compose("tradeoff", return_hydra_config=True)
    (override,) = OverridesParser.create().parse_overrides([f"+tradeoff={cfg.hydra.sweeper.params['+tradeoff']}"])
    listed = [str(v) for v in override.sweep_string_iterator()]
    files = sorted(p.stem for p in (CONF / "tradeoff").glob("*.yaml"))
    assert sorted(listed) == sorted(set(files) - {"raster_gsplat"})  # gsplat needs CUDA: the GPU list adds it
    assert set(files) == {"baseline", *KNOBS}


@pytest.mark.parametrize("profile", ["ablation", "gpu"])
@pytest.mark.parametrize("point", sorted(KNOBS))
def test_each_point_changes_exactly_its_knob(point: str, profile: str) -> None:
    base = _compose("baseline", profile)
    cfg = _compose(point, profile)
    for key in set(cfg) - {"paths"}:  # every interpolation resolves (paths need a running Hydra job)
        if OmegaConf.is_config(cfg[key]):
            OmegaConf.to_container(cfg[key], resolve=True)
    a, b = flat(OmegaConf.to_container(base)), flat(OmegaConf.to_container(cfg))
    changed = {k for k in a.keys() | b.keys() if a.get(k, "<absent>") != b.get(k, "<absent>")} - {"task_name"}
    allowed = KNOBS[point]

    def covered(key: str) -> bool:
        return any(key == k or (k.endswith(".") and key.startswith(k)) for k in allowed)

    assert all(covered(k) for k in changed), sorted(k for k in changed if not covered(k))
    assert all(any(c == k or (k.endswith(".") and c.startswith(k)) for c in changed) for k in allowed), changed
    assert cfg.task_name == f"tradeoff_{point}"
    # the resolved values are the knob's: relative to the profile, so the same file serves CPU and GPU sizes
    p = base.profile
    resolved = {
        "gaussians_half": ("gaussians.num", p.num_gaussians // 2),
        "gaussians_quarter": ("densifier.max_gaussians", p.max_gaussians // 4),
        "gaussians_double": ("gaussians.num", 2 * p.num_gaussians),
        "resolution_half": ("data.split_overrides.train.downscale", 2),
        "steps_half": ("trainer.max_steps", p.max_steps // 2),
        "sh1": ("gaussians.sh_degree", 1),
    }
    if point in resolved:
        key, value = resolved[point]
        assert OmegaConf.select(cfg, key) == value
    if point in ("steps_half", "preset_quick"):  # the whole schedule at half the length (these profiles' steps halve)
        assert {k: OmegaConf.select(cfg, k) for k in SCHEDULE} == {k: OmegaConf.select(base, k) // 2 for k in SCHEDULE}


def test_baseline_is_paper_full() -> None:
    with initialize_config_module("framework.conf", version_base="1.3"):
        direct = compose("train", overrides=["+experiment=paper_full", "profile=ablation"])
        base = compose("tradeoff", overrides=["+tradeoff=baseline", "profile=ablation"])
    assert base.task_name == "tradeoff_baseline"
    base.task_name = direct.task_name
    assert base == direct


def test_resolution_half_trains_small_and_evaluates_on_the_full_size_images(tmp_path, monkeypatch) -> None:
    """Every point is measured against the same ground truth: only the training split is downscaled."""
    from framework.build import build_split

    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(tmp_path))
    with initialize_config_module("framework.conf", version_base="1.3"):
        cfg = compose(
            "tradeoff",
            overrides=[
                "+tradeoff=resolution_half",
                "profile=cpu",
                "profile.resolution=32",
                "profile.num_views=4",
                "profile.num_frames=6",
                "data.supersample=1",
            ],
        )
    train, held_out = build_split(cfg.data, "train"), build_split(cfg.data, "novel_view")
    full = OmegaConf.select(cfg, "data.resolution")
    assert train[0].image.shape[-3:-1] == (full // 2, full // 2)
    assert held_out[0].image.shape[-3:-1] == (full, full)
    assert train[0].cameras.K[..., 0, 0] * 2 == pytest.approx(float(held_out[0].cameras.K[..., 0, 0]), rel=1e-6)

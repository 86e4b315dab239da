"""`python -m framework.report`: known runs give a known table and verdicts; a tiny real two-row, two-seed sweep run in
two parts (one per seed) reports as one table."""

from __future__ import annotations

import csv
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from framework.evaluation.run_record import SCHEMA, load_run_record, metrics_from_summary, write_run_record
from framework.reporting.runs import ReportError, find_runs, variant_of
from framework.reporting.stats import Spread, against_reference, difference, spread, verdict
from framework.reporting.table4 import PAPER, build_table, write_report

SHARED = ["data=synthetic_studio_realistic", "profile=ablation"]
# novel-view / novel-pose PSNR per seed (whole image); body-box PSNR is 5 dB lower; SSIM and LPIPS fixed
PSNR = {
    "paper_full": ([30.0, 30.2, 29.8], [29.0, 29.1, 28.9]),
    "no_corrector": ([29.0, 29.2, 28.8], [28.0, 28.1, 27.9]),  # -1.0 / -1.0: the paper's sign, beyond 2 sigma
    "no_alpha_loss": ([30.1, 30.3, 29.9], [29.05, 29.15, 28.95]),  # +0.1 / +0.05: within 2 sigma
    "all_sh_correction": ([31.0, 31.2, 30.8], [29.0, 29.1, 28.9]),  # +1.0 vs the paper's -0.01: disagrees
    "no_weight_std_loss": ([30.0, 30.2, 29.8], [27.0, 27.1, 26.9]),  # 0 vs the paper's 0.00: agrees; -2.0 agrees
}


def _write_runs(root: Path, seeds: list[int]) -> None:
    for experiment, (nv, np_) in PSNR.items():
        for s in seeds:
            run = root / f"+experiment={experiment},seed={s}"
            summary = {
                "novel_view/psnr": nv[s],
                "novel_pose/psnr": np_[s],
                "novel_view/bbox/psnr": nv[s] - 5,
                "novel_pose/bbox/psnr": np_[s] - 5,
                "novel_view/ssim": 0.97,
                "novel_pose/ssim": 0.96,
                "novel_view/lpips_alex": 0.05,
                "novel_pose/lpips_alex": 0.06,
            }
            write_run_record(
                run,
                experiment=experiment,
                config_name="ablations",
                overrides=[f"+experiment={experiment}", f"seed={s}", *SHARED, "threads=1"],
                seed=s,
                profile="ablation",
                data="synthetic_studio",
                steps=1800,
                max_steps=1800,
                train_seconds=480.0 + s,
                run_seconds=540.0,
                num_gaussians=9000,
                metrics=metrics_from_summary(summary),
            )


def _tiny_record(folder: Path, experiment: str, seed: int, summary: dict[str, float], config_name: str) -> None:
    """A results.json of a 10-step run with the evaluation `summary`, for tests that need only its metrics."""
    write_run_record(
        folder,
        experiment=experiment,
        config_name=config_name,
        overrides=[f"+experiment={experiment}", f"seed={seed}", *SHARED],
        seed=seed,
        profile="ablation",
        data="synthetic_studio",
        steps=10,
        max_steps=10,
        train_seconds=1.0,
        run_seconds=1.0,
        num_gaussians=10,
        metrics=metrics_from_summary(summary),
    )


@pytest.fixture()
def parts(tmp_path: Path) -> list[Path]:
    """The sweep in two parts, as two sweep directories: seeds 0 and 1, then seed 2."""
    _write_runs(tmp_path / "part1", [0, 1])
    _write_runs(tmp_path / "part2", [2])
    return [tmp_path / "part1", tmp_path / "part2"]


def test_statistics_closed_forms():
    s = spread([30.0, 30.2, 29.8, None, float("nan")])
    assert (s.mean, s.n) == (pytest.approx(30.0), 3) and s.std == pytest.approx(0.2)
    d = difference(Spread(29.0, 0.2, 3), Spread(30.0, 0.2, 3))
    assert d.delta == pytest.approx(-1.0) and d.sigma == pytest.approx((0.04 / 3 * 2) ** 0.5)
    assert verdict(d, -3.82) == "agrees" and verdict(d, 0.5) == "disagrees"
    assert verdict(difference(Spread(30.1, 0.2, 3), Spread(30.0, 0.2, 3)), -0.11) == "within noise"
    assert verdict(difference(Spread(30.0, 0.2, 3), Spread(30.0, 0.2, 3)), 0.0) == "agrees"
    assert verdict(difference(Spread(29.0, 0.2, 3), Spread(30.0, 0.2, 3)), 0.0) == "disagrees"
    assert verdict(difference(Spread(29.0, float("nan"), 1), Spread(30.0, 0.2, 3)), -1.0) == "needs 2 seeds"
    assert verdict(d, None) is None


def test_rows_outside_the_papers_table_are_judged_against_the_reference_alone():
    assert against_reference(difference(Spread(31.0, 0.2, 3), Spread(30.0, 0.2, 3))) == "better"
    assert against_reference(difference(Spread(29.0, 0.2, 3), Spread(30.0, 0.2, 3))) == "worse"
    assert against_reference(difference(Spread(30.2, 0.2, 3), Spread(30.0, 0.2, 3))) == "within noise"  # 0.2 < 2σ
    assert against_reference(difference(Spread(31.0, float("nan"), 1), Spread(30.0, 0.2, 3))) == "needs 2 seeds"


def test_paper_forms_report_judges_each_form_against_paper_full(tmp_path):
    """kind=paper_forms: the project's forms are not Table 4 rows, so each is better / worse / within noise."""
    from framework.reporting.kinds import REPORT_KINDS

    forms = {"paper_full": 0.0, "paper_full_alpha_l1": -1.0, "paper_full_half_dssim": 0.05, "splatrig_full": 1.0}
    for experiment, shift in forms.items():
        for s, noise in enumerate((0.0, 0.2, -0.2)):
            summary = {"novel_view/psnr": 30.0 + shift + noise, "novel_pose/psnr": 29.0 + shift + noise}
            _tiny_record(tmp_path / "runs" / f"{experiment}{s}", experiment, s, summary, "paper_forms")
    markdown, _ = REPORT_KINDS["paper_forms"](find_runs([tmp_path / "runs"]), tmp_path / "out")
    assert markdown.startswith("# The project's forms against the paper's")
    lines = list(csv.DictReader(io.StringIO((tmp_path / "out" / "paper_forms.csv").read_text())))
    judged = {r["experiment"]: r["verdict"] for r in lines if r["metric"] == "psnr" and r["region"] == "image"}
    assert judged == {
        "paper_full": "",
        "paper_full_alpha_l1": "worse",
        "paper_full_half_dssim": "within noise",
        "splatrig_full": "better",
    }
    assert (tmp_path / "out" / "paper_forms.png").is_file()


def test_paper_ssim_and_lpips_deltas_where_the_paper_gives_them(tmp_path):
    """The paper's Table 4: complete model SSIM 0.989 / LPIPS 0.036 (novel view), only foreground 0.291 / 0.163."""
    for experiment in ("paper_full", "foreground_only_loss"):
        for s in (0, 1):
            summary = {
                "novel_view/psnr": 30.0,
                "novel_pose/psnr": 29.0,
                "novel_view/ssim": 0.9 + 0.01 * s,
                "novel_pose/ssim": 0.9,
                "novel_view/lpips_alex": 0.05,
                "novel_pose/lpips_alex": 0.06,
            }
            _tiny_record(tmp_path / f"{experiment}{s}", experiment, s, summary, "ablations")
    rows = {r.experiment: r for r in build_table(find_runs([tmp_path])).rows}
    cells = rows["foreground_only_loss"].cells
    assert cells[("image", "novel_view", "ssim")].paper_delta == pytest.approx(0.291 - 0.989)
    assert cells[("image", "novel_view", "lpips_alex")].paper_delta == pytest.approx(0.163 - 0.036)
    assert cells[("image", "novel_view", "ssim")].verdict is None  # verdicts are on PSNR
    assert cells[("image", "novel_pose", "ssim")].paper_delta is None  # not held for this split
    assert cells[("image", "novel_view", "psnr")].paper_delta == pytest.approx(24.22 - 33.32)


def test_a_split_recorded_later_is_judged_against_the_papers_split(parts):
    """`evaluate ... record_as=novel_pose_true_poses` adds a split to a run's record; the table shows it for every row
    and judges it against the paper's novel-pose Δ (w/o F_a: -3.42 dB)."""
    from framework.evaluation.run_record import record_metrics

    truth = {"paper_full": [31.0, 31.1, 30.9], "no_corrector": [30.0, 30.1, 29.9]}  # -1.0 dB: agrees
    for part, seeds in zip(parts, ([0, 1], [2]), strict=True):
        for experiment, values in truth.items():
            for s in seeds:
                run = part / f"+experiment={experiment},seed={s}"
                record_metrics(run, "novel_pose_true_poses", {"image": {"psnr": values[s]}})
                assert (
                    load_run_record(run / "results.json")["metrics"]["novel_pose"]["image"]["psnr"]
                    == PSNR[experiment][1][s]
                )  # the training's own splits are kept
    table = build_table(find_runs(parts))
    assert [name for name, _ in table.splits] == ["novel_view", "novel_pose", "novel_pose_true_poses"]
    cell = {r.experiment: r for r in table.rows}["no_corrector"].cells[("image", "novel_pose_true_poses", "psnr")]
    assert cell.diff.delta == pytest.approx(-1.0) and cell.paper_delta == pytest.approx(29.99 - 33.41)
    assert cell.verdict == "agrees"
    missing = {r.experiment: r for r in table.rows}["no_alpha_loss"].cells[("image", "novel_pose_true_poses", "psnr")]
    assert missing.value.n == 0 and missing.verdict is None  # a row nobody re-evaluated has no cell


def test_runs_from_two_parts_give_the_known_table(parts, tmp_path):
    runs = find_runs(parts)
    assert len(runs) == 15 and runs[0].variant == tuple(sorted(["+experiment=all_sh_correction", *SHARED]))
    table = build_table(runs)
    assert table.shared == tuple(sorted(SHARED))
    rows = {r.experiment: r for r in table.rows}
    assert [r.experiment for r in table.rows] == [
        "paper_full",
        "all_sh_correction",
        "no_corrector",
        "no_alpha_loss",
        "no_weight_std_loss",
    ]  # the paper's order

    def cell(row, split, region="image"):
        return rows[row].cells[(region, split, "psnr")]

    full = cell("paper_full", "novel_view")
    assert full.value.mean == pytest.approx(30.0) and full.value.std == pytest.approx(0.2) and full.diff is None
    c = cell("no_corrector", "novel_view")
    assert c.diff.delta == pytest.approx(-1.0) and c.paper_delta == pytest.approx(29.50 - 33.32)
    assert c.verdict == "agrees" and cell("no_corrector", "novel_pose").verdict == "agrees"
    assert cell("no_alpha_loss", "novel_view").verdict == "within noise"
    assert cell("all_sh_correction", "novel_view").verdict == "disagrees"
    assert cell("no_weight_std_loss", "novel_view").verdict == "agrees"  # the paper: +0.00, ours: 0
    assert cell("no_weight_std_loss", "novel_pose").verdict == "agrees"  # the paper: -0.37, ours: -2.0
    assert cell("no_corrector", "novel_view", "body_box").diff.delta == pytest.approx(-1.0)

    markdown, paths = write_report(runs, tmp_path / "report")
    assert "w/o F_a (no_corrector)" in markdown and "29.00 ± 0.20 (Δ -1.00 ± 0.16; paper -3.82)" in markdown
    assert "## body box" in markdown and "data=synthetic_studio_realistic profile=ablation" in markdown
    out = tmp_path / "report"
    lines = list(csv.DictReader(io.StringIO((out / "table4.csv").read_text())))
    nv = next(
        r
        for r in lines
        if r["experiment"] == "no_corrector"
        and r["split"] == "novel_view"
        and r["metric"] == "psnr"
        and r["region"] == "image"
    )
    assert float(nv["delta"]) == pytest.approx(-1.0) and nv["verdict"] == "agrees" and nv["seeds"] == "0 1 2"
    assert (out / "table4.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert list((out / "tb").glob("events.out.tfevents.*"))


def test_report_refuses_what_it_cannot_compare(parts, tmp_path):
    with pytest.raises(ReportError, match="run twice"):
        build_table(find_runs([*parts, parts[1]]))  # the same part twice: every seed-2 run twice
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ReportError, match="no results.json"):
        find_runs([empty])
    for run in (
        parts[0] / "+experiment=paper_full,seed=0",
        parts[0] / "+experiment=paper_full,seed=1",
        parts[1] / "+experiment=paper_full,seed=2",
    ):
        (run / "results.json").unlink()
    with pytest.raises(ReportError, match="paper_full"):
        build_table(find_runs(parts))
    bad = parts[0] / "+experiment=no_corrector,seed=0" / "results.json"
    bad.write_text(json.dumps({"schema": "other/9"}))
    with pytest.raises(Exception, match="schema"):
        load_run_record(bad)


def test_variant_ignores_seed_and_bookkeeping():
    assert variant_of(["seed=3", "+experiment=a", "paths.root=/x", "threads=1", "data.workers=1", "b=2"]) == (
        "+experiment=a",
        "b=2",
    )


def test_report_command(parts, tmp_path):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    runs = ",".join(map(str, parts))
    cmd = [sys.executable, "-m", "framework.report", f"runs=[{runs}]", f"out={tmp_path / 'r'}"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "Table 4" in proc.stdout and (tmp_path / "r" / "table4.md").is_file()
    proc = subprocess.run(
        [sys.executable, "-m", "framework.report", f"runs={tmp_path / 'nothing'}"],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 2 and "no such directory" in proc.stderr and "Traceback" not in proc.stderr


def test_paper_table_has_every_row_of_the_sweep():
    from omegaconf import OmegaConf

    sweep = OmegaConf.load(Path(__file__).resolve().parents[1] / "sweeps" / "ablations.yaml")
    rows = [r.strip() for r in str(sweep.hydra.sweeper.params["+experiment"]).split(",")]
    assert sorted(rows) == sorted(PAPER) and str(sweep.hydra.sweeper.params.seed) == "0,1,2"
    assert sweep.hydra.sweeper.params.data == "synthetic_studio_realistic"


# A real sweep at toy size through the sweep config: 2 rows x 2 seeds, run as two parts (one seed each). Keys of groups
# the experiment chooses (data, deformer) take `++`: a multirun first composes the config without the swept
# experiment, where those groups are still train.yaml's defaults.
TINY_SWEEP = [
    "body=procedural",
    "++data.body=procedural",
    "++data.resolution=40",
    "++data.num_views=4",
    "++data.num_frames=6",
    "++data.supersample=1",
    "++data.workers=1",
    "++deformer.grid_resolution=10",
    "gaussians.num=200",
    "trainer.max_steps=12",
    "stages.stage1_steps=4",
    "trainer.val_every=100",
    "densifier.first_reset=3",
    "densifier.reset_every=4",
    "densifier.refine_stop=10",
    "densifier.reset_restart=4",
    "densifier.refine_start=2",
    "densifier.refine_every=4",
    "callbacks.checkpoint_every=100",
    "callbacks.image_every=0",
    "callbacks.progress_bar=false",
    "eval.metrics=[psnr,ssim]",
    "threads=1",
    "+experiment=paper_full,no_corrector",
]


def test_tiny_real_sweep_in_two_parts_reports(tmp_path: Path):
    env = dict(os.environ, SPLATRIG_CACHE_DIR=str(tmp_path / "cache"), PYTHONUNBUFFERED="1")
    parts = []
    for seed in (0, 1):
        part = tmp_path / f"part{seed}"
        cmd = [
            sys.executable,
            "-m",
            "framework.train",
            "-m",
            "--config-name",
            "ablations",
            *TINY_SWEEP,
            f"seed={seed}",
            f"hydra.sweep.dir={part}",
        ]
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900, cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr[-3000:]
        parts.append(part)
    records = sorted(parts[0].rglob("results.json")) + sorted(parts[1].rglob("results.json"))
    assert len(records) == 4
    record = load_run_record(records[0])
    assert record["schema"] == SCHEMA and record["config_name"] == "ablations" and record["steps"] == 12
    assert "data=synthetic_studio_realistic" in record["overrides"] and record["train_seconds"] > 0
    for split in ("novel_view", "novel_pose"):
        for region in ("image", "body_box"):
            assert set(record["metrics"][split][region]) == {"psnr", "ssim"}
    assert record["metrics"]["novel_view"]["body_box"]["psnr"] < record["metrics"]["novel_view"]["image"]["psnr"]
    markdown, _ = write_report(find_runs(parts), tmp_path / "report")
    rows = {r.experiment: r for r in build_table(find_runs(parts)).rows}
    assert set(rows) == {"paper_full", "no_corrector"} and rows["no_corrector"].seeds == (0, 1)
    assert rows["no_corrector"].cells[("image", "novel_pose", "psnr")].verdict in (
        "agrees",
        "disagrees",
        "within noise",
    )
    assert "w/o F_a (no_corrector)" in markdown

"""The paper's Table 4 from our runs: rows = ablations, columns = novel view and novel pose PSNR / SSIM / LPIPS; each
cell the mean +- std over seeds with the difference to paper_full, the paper's difference beside it (PSNR for every
row; SSIM and LPIPS where `PAPER_SSIM_LPIPS` holds the paper's values), and a verdict per row and split on PSNR
(`framework.reporting.stats.verdict`). One table on whole images (the paper's protocol)
and one inside the body box (Neural Body / Animatable NeRF).

Rows are variants (`framework.reporting.runs`): runs that differ only by seed. Overrides every variant shares (the
data, the profile) are stated once; a row's label is its experiment plus the overrides that set it apart, so extra
rows (e.g. paper_full with the paper's alpha norm) sit beside the Table 4 rows, compared with paper_full too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from framework.atomic import atomic_write_text
from framework.plugins import format_table
from framework.reporting.csv_text import csv_text
from framework.reporting.figures import save_png
from framework.reporting.runs import ReportError, Run, group_runs
from framework.reporting.stats import Difference, Spread, against_reference, difference, spread, verdict

REFERENCE = "paper_full"
SPLITS = (("novel_view", "novel view"), ("novel_pose", "novel pose"))
#: Splits a run may record after training (`framework.evaluate ... record_as=<name>`), shown when any run has them:
#: name -> (label, the paper's split whose Δ they are judged against). The studio's true poses remove the pose-fit
#: noise of its stored poses from the held-out motion, so a row is judged on the model rather than on that noise.
LATER_SPLITS = {"novel_pose_true_poses": ("novel pose, true poses", "novel_pose")}
REGIONS = (("image", "whole image"), ("body_box", "body box"))
#: (metric key in results.json, column label, decimals)
METRICS = (("psnr", "PSNR", 2), ("ssim", "SSIM", 4), ("lpips_alex", "LPIPS", 4))


@dataclass(frozen=True)
class PaperRow:
    experiment: str
    label: str
    psnr: dict[str, float]  # split -> the paper's PSNR (ZJU-MoCap 313)


#: The paper's Table 4 (ZJU-MoCap 313, PSNR), in its order.
PAPER_TABLE4: tuple[PaperRow, ...] = tuple(
    PaperRow(e, label, {"novel_view": nv, "novel_pose": np_})
    for e, label, nv, np_ in (
        ("paper_full", "complete model", 33.32, 33.41),
        ("simple_3dgs_lbs", "simple 3DGS+LBS", 28.56, 29.56),
        ("posenc_instead_of_latent", "positional encoding", 30.03, 30.32),
        ("foreground_only_loss", "only foreground", 24.22, 24.26),
        ("all_sh_correction", "all-order SH", 33.31, 32.73),
        ("no_first_stage", "w/o first stage", 25.80, 25.81),
        ("no_joint_optimisation", "w/o joint optimisation", 32.42, 32.19),
        ("no_boundary_mask", "w/o boundary mask", 32.10, 32.41),
        ("no_corrector", "w/o F_a", 29.50, 29.99),
        ("no_alpha_loss", "w/o L_alpha", 33.21, 32.01),
        ("no_weight_std_loss", "w/o L_w", 33.32, 33.04),
    )
)
PAPER = {row.experiment: row for row in PAPER_TABLE4}
#: The paper's Table 4 SSIM and LPIPS that this table holds: (experiment, split, metric) -> value.
PAPER_SSIM_LPIPS: dict[tuple[str, str, str], float] = {
    ("paper_full", "novel_view", "ssim"): 0.989,
    ("paper_full", "novel_view", "lpips_alex"): 0.036,
    ("paper_full", "novel_pose", "ssim"): 0.987,
    ("paper_full", "novel_pose", "lpips_alex"): 0.036,
    ("foreground_only_loss", "novel_view", "ssim"): 0.291,
    ("foreground_only_loss", "novel_view", "lpips_alex"): 0.163,
}


def paper_delta(experiment: str, split: str, metric: str) -> float | None:
    """The paper's row minus its complete model, where the paper's table (as held here) gives both."""
    split = LATER_SPLITS[split][1] if split in LATER_SPLITS else split
    if metric == "psnr":
        row = PAPER.get(experiment)
        return None if row is None else round(row.psnr[split] - PAPER[REFERENCE].psnr[split], 2)
    value, ref = PAPER_SSIM_LPIPS.get((experiment, split, metric)), PAPER_SSIM_LPIPS.get((REFERENCE, split, metric))
    return None if value is None or ref is None else round(value - ref, 3)


@dataclass(frozen=True)
class Cell:
    value: Spread
    diff: Difference | None  # None on the reference row
    paper_delta: float | None  # Table 4 rows only; SSIM and LPIPS where PAPER_SSIM_LPIPS has them
    verdict: str | None


@dataclass(frozen=True)
class Row:
    key: tuple[str, ...]  # the variant's own overrides (beyond the shared ones)
    experiment: str
    label: str
    paper: PaperRow | None
    seeds: tuple[int, ...]
    cells: dict[tuple[str, str, str], Cell]  # (region, split, metric) -> cell


@dataclass(frozen=True)
class Table4:
    rows: list[Row]
    shared: tuple[str, ...]  # overrides every run shares
    runs: list[Run]
    splits: tuple[tuple[str, str], ...] = SPLITS  # (split, label): SPLITS and the later splits some run recorded


def _label(experiment: str, extras: tuple[str, ...]) -> str:
    paper = PAPER.get(experiment)
    base = f"{paper.label} ({experiment})" if paper is not None else experiment
    return base + (" + " + ", ".join(extras) if extras else "")


def build_table(runs: list[Run]) -> Table4:
    """Group the runs into rows and compute every cell (see the module docstring)."""
    groups = group_runs(runs)
    variants = list(groups)
    shared = tuple(sorted(set(variants[0]).intersection(*map(set, variants[1:])))) if variants else ()
    own = {v: tuple(x for x in v if x not in shared) for v in variants}

    def extras(v: tuple[str, ...]) -> tuple[str, ...]:
        return tuple(x for x in own[v] if not x.lstrip("+").startswith("experiment="))

    references = [v for v in variants if groups[v][0].experiment == REFERENCE and not extras(v)]
    if not references:
        found = sorted({r.experiment for r in runs})
        raise ReportError(
            f"table4 compares every row with {REFERENCE}, but the runs given hold none (experiments: {found}); "
            f"include the sweep directory with the {REFERENCE} runs."
        )
    if len(references) > 1:
        raise ReportError(
            f"table4 found {len(references)} differently configured sets of {REFERENCE} runs ("
            + "; ".join(" ".join(v) for v in references)
            + "); report each configuration on its own (pass only its sweep directories)."
        )
    ref_runs = groups[references[0]]

    def cell_values(members: list[Run], region: str, split: str, metric: str) -> Spread:
        return spread(r.metric(split, region, metric) for r in members)

    recorded = {name for r in runs for name in r.record["metrics"]}
    later = [(name, label) for name, (label, _) in LATER_SPLITS.items() if name in recorded]
    splits = (*SPLITS, *later)
    rows = []
    order = {row.experiment: i for i, row in enumerate(PAPER_TABLE4)}
    for v in sorted(variants, key=lambda v: (bool(extras(v)), order.get(groups[v][0].experiment, 99), own[v])):
        members = groups[v]
        experiment = members[0].experiment
        paper = PAPER.get(experiment) if not extras(v) else None
        is_ref = v == references[0]
        cells = {}
        for region, _ in REGIONS:
            for split, _ in splits:
                for metric, _, _ in METRICS:
                    value = cell_values(members, region, split, metric)
                    if is_ref:
                        cells[(region, split, metric)] = Cell(value, None, None, None)
                        continue
                    diff = difference(value, cell_values(ref_runs, region, split, metric))
                    delta = paper_delta(experiment, split, metric) if paper is not None else None
                    judged = None
                    if metric == "psnr":
                        judged = verdict(diff, delta) if paper is not None else against_reference(diff)
                    cells[(region, split, metric)] = Cell(value, diff, delta, judged)
        rows.append(
            Row(own[v], experiment, _label(experiment, extras(v)), paper, tuple(sorted(r.seed for r in members)), cells)
        )
    return Table4(rows, shared, runs, splits)


# ----------------------------------------------------------------------------------------------------- text
def _num(x: float, decimals: int, signed: bool = False) -> str:
    if x is None or math.isnan(x):
        return "-"
    return f"{x:+.{decimals}f}" if signed else f"{x:.{decimals}f}"


def cell_text(cell: Cell, decimals: int) -> str:
    """ "33.10 ± 0.12" on the reference row; "32.80 ± 0.10 (Δ -0.30 ± 0.09; paper -0.91)" elsewhere."""
    text = f"{_num(cell.value.mean, decimals)} ± {_num(cell.value.std, decimals)}"
    if cell.diff is None:
        return text
    inner = f"Δ {_num(cell.diff.delta, decimals, True)} ± {_num(cell.diff.sigma, decimals)}"
    if cell.paper_delta is not None:
        inner += f"; paper {cell.paper_delta:+.{min(decimals, 3)}f}"
    return f"{text} ({inner})"


def region_markdown(table: Table4, region: str) -> str:
    header = ["row", "seeds"]
    header += [f"{s_label} {m_label}" for _, s_label in table.splits for _, m_label, _ in METRICS]
    header += [f"verdict {s_label}" for _, s_label in table.splits]
    lines = []
    for row in table.rows:
        cells = [row.label, ",".join(map(str, row.seeds))]
        cells += [cell_text(row.cells[(region, s, m)], d) for s, _ in table.splits for m, _, d in METRICS]
        cells += [row.cells[(region, s, "psnr")].verdict or "" for s, _ in table.splits]
        lines.append(tuple(cells))
    return format_table(lines, tuple(header), pad=False)  # 14 columns: aligned, the file is mostly spaces


def to_markdown(table: Table4, title: str = "Table 4 (ablations), reproduced") -> str:
    seconds = [float(r.record.get("train_seconds", math.nan)) for r in table.runs]
    steps = sorted({int(r.record.get("steps", 0)) for r in table.runs})
    parts = [
        f"# {title}",
        "",
        f"{len(table.runs)} runs; settings shared by every row: `{' '.join(table.shared) or '(none)'}`; "
        f"training steps {', '.join(map(str, steps))}; training time per run {_num(spread(seconds).mean / 60, 1)} "
        f"± {_num(spread(seconds).std / 60, 1)} min.",
        "",
        "Each cell: mean ± std over seeds; on the other rows (Δ = row − complete model ± σ; the paper's Δ), with "
        "σ = sqrt(s_row²/n_row + s_full²/n_full), the seed noise of the difference of two means. Verdict (PSNR): "
        "**agrees** = same sign as the paper's Δ and |Δ| > 2σ; **disagrees** = opposite sign beyond 2σ (or a change "
        "beyond 2σ where the paper saw none); **within noise** = |Δ| ≤ 2σ (where the paper saw no change, that "
        "agrees). A row outside the paper's table is judged against the complete model alone: **better** / **worse** "
        "beyond 2σ, otherwise within noise. The paper's SSIM / LPIPS Δs are shown where this report holds the "
        "paper's values (complete model, only foreground's novel view); verdicts are on PSNR. A body-box PSNR Δ equals "
        "the whole-image one when both models leave the background exactly black (the background then "
        "adds the same constant to every row's PSNR); SSIM and LPIPS inside the box do differ.",
    ]
    for region, r_label in REGIONS:
        parts += ["", f"## {r_label}", "", region_markdown(table, region)]
    return "\n".join(parts) + "\n"


def to_csv(table: Table4) -> str:
    header = (
        "region",
        "row",
        "experiment",
        "split",
        "metric",
        "n",
        "seeds",
        "mean",
        "std",
        "delta",
        "sigma",
        "paper_delta",
        "verdict",
    )
    rows = (
        (
            region,
            row.label,
            row.experiment,
            split,
            metric,
            c.value.n,
            " ".join(map(str, row.seeds)),
            c.value.mean,
            c.value.std,
            "" if c.diff is None else c.diff.delta,
            "" if c.diff is None else c.diff.sigma,
            "" if c.paper_delta is None else c.paper_delta,
            c.verdict or "",
        )
        for row in table.rows
        for (region, split, metric), c in row.cells.items()
    )
    return csv_text(header, rows)


# ----------------------------------------------------------------------------------------------------- chart
def figure(table: Table4):
    """Our PSNR Δ (whole image and body box, error bars 2σ) beside the paper's Δ, one panel per split."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in table.rows if any(c.diff is not None for c in r.cells.values())]
    fig, axes = plt.subplots(1, len(table.splits), figsize=(max(11.0, 1.1 * len(rows) + 5), 5.5), sharey=True)
    width = 0.27
    for ax, (split, s_label) in zip(axes, table.splits, strict=True):
        xs = range(len(rows))
        for k, (region, r_label) in enumerate(REGIONS):
            cells = [r.cells[(region, split, "psnr")] for r in rows]
            ax.bar(
                [x + (k - 1) * width for x in xs],
                [c.diff.delta for c in cells],
                width,
                yerr=[2 * c.diff.sigma if not math.isnan(c.diff.sigma) else 0 for c in cells],
                capsize=2,
                label=f"ours, {r_label} (±2σ)",
            )
        paper = [r.cells[("image", split, "psnr")].paper_delta for r in rows]
        if any(p is not None for p in paper):  # rows outside the paper's table have no bar to draw
            ax.bar(
                [x + width for x in xs],
                [math.nan if p is None else p for p in paper],
                width,
                color="0.55",
                label="paper (ZJU-MoCap 313)",
            )
        ax.axhline(0.0, color="k", lw=0.8)
        ax.set_xticks(list(xs))
        ax.set_xticklabels(
            [r.experiment if not r.key or r.paper else r.label for r in rows], rotation=60, ha="right", fontsize=8
        )
        ax.set_title(f"{s_label}\nΔ PSNR to {REFERENCE}")
        ax.grid(axis="y", alpha=0.3)
    axes[0].set_ylabel("Δ PSNR (dB)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    return fig


def log_tensorboard(table: Table4, markdown: str, fig, log_dir: Path) -> None:
    """The table as text, the chart as a figure and every Δ PSNR as a scalar, under `log_dir`."""
    from torch.utils.tensorboard import SummaryWriter

    with SummaryWriter(log_dir=str(log_dir)) as writer:
        writer.add_text("table4", markdown)
        writer.add_figure("table4/delta_psnr", fig, close=False)
        for row in table.rows:
            for (region, split, metric), c in row.cells.items():
                if c.diff is not None and metric == "psnr" and not math.isnan(c.diff.delta):
                    writer.add_scalar(f"table4/{region}/{split}/{row.label}/delta_psnr", c.diff.delta)


def write_report(
    runs: list[Run], out_dir: Path, name: str = "table4", title: str = "Table 4 (ablations), reproduced"
) -> tuple[str, list[Path]]:
    """<name>.md, <name>.csv, <name>.png and a TensorBoard log (tb/) in `out_dir`; returns (markdown, paths). The
    paper-forms report is this one under another name and title: its rows are paper_full's variants too."""
    table = build_table(runs)
    markdown = to_markdown(table, title)
    out_dir = Path(out_dir)
    paths = [
        atomic_write_text(out_dir / f"{name}.md", markdown),
        atomic_write_text(out_dir / f"{name}.csv", to_csv(table)),
    ]
    fig = figure(table)
    paths.append(save_png(fig, out_dir / f"{name}.png"))
    log_tensorboard(table, markdown, fig, out_dir / "tb")
    paths.append(out_dir / "tb")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return markdown, paths

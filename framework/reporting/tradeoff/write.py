"""write_report: the trade-off report kind (`python -m framework.report kind=tradeoff`), putting points, budgets,
gains, text and plots together into the files of `out_dir` and a TensorBoard log."""

from __future__ import annotations

from pathlib import Path

from framework.atomic import atomic_write_text
from framework.reporting.figures import save_png
from framework.reporting.runs import Run
from framework.reporting.tradeoff.budgets import DEFAULT_BUDGETS, parse_budget, presets_by_point, recommendations
from framework.reporting.tradeoff.gains import knob_gains
from framework.reporting.tradeoff.plots import figure, overview
from framework.reporting.tradeoff.points import OBJECTIVES, PLANES, build_points
from framework.reporting.tradeoff.text import recommendations_csv, to_csv, to_markdown

OVERVIEW = "tradeoff_overview.png"  # the four objectives' planes in one picture


def write_report(runs: list[Run], out_dir: Path, budgets: list[str] | None = None) -> tuple[str, list[Path]]:
    """tradeoff.md, tradeoff.csv, recommendations.csv, tradeoff_<plane>.png, tradeoff_overview.png and a TensorBoard
    log (tb/) in `out_dir`."""
    import matplotlib.pyplot as plt
    from torch.utils.tensorboard import SummaryWriter

    parsed = [parse_budget(b) for b in (budgets or DEFAULT_BUDGETS)]
    points = build_points(runs)
    recs = recommendations(points, parsed, presets_by_point())
    markdown = to_markdown(points, runs, recs, knob_gains(points))
    out_dir = Path(out_dir)
    paths = [
        atomic_write_text(out_dir / "tradeoff.md", markdown),
        atomic_write_text(out_dir / "tradeoff.csv", to_csv(points)),
        atomic_write_text(out_dir / "recommendations.csv", recommendations_csv(recs)),
    ]
    with SummaryWriter(log_dir=str(out_dir / "tb")) as writer:
        writer.add_text("tradeoff", markdown)
        for objective in PLANES:
            fig = figure(points, objective)
            paths.append(save_png(fig, out_dir / objective.file, dpi=100))
            writer.add_figure(f"tradeoff/{Path(objective.file).stem}", fig, close=False)
            plt.close(fig)
        fig = overview(points, OBJECTIVES)
        paths.append(save_png(fig, out_dir / OVERVIEW, dpi=100))
        plt.close(fig)
    paths.append(out_dir / "tb")
    return markdown, paths

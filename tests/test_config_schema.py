"""The training config's types (framework/config_schema.py): composition checks values, and a stored config (an older
checkpoint's) reads through the same types, a key it lacks as the schema's default."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_module
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf
from omegaconf.errors import ValidationError

from framework.cli import composition_message
from framework.config_schema import Train, training_settings
from framework.lightning.checkpoint_io import read_checkpoint
from framework.paths import DEMO


def _compose(overrides: list[str]):
    with initialize_config_module(config_module="framework.conf", version_base="1.3"):
        return compose(config_name="train", overrides=["profile=cpu", *overrides])


def test_composed_values_have_the_schema_types() -> None:
    cfg = _compose(["+experiment=paper_full", "seed=3", "gaussians.opacity=0.2"])
    assert OmegaConf.get_type(cfg.trainer) is not dict and cfg.seed == 3 and cfg.gaussians.opacity == 0.2
    assert isinstance(cfg.trainer.max_steps, int) and cfg.trainer.max_steps == cfg.profile.max_steps


@pytest.mark.parametrize(
    ("override", "line"),
    [
        ("trainer.max_steps=abc", "trainer.max_steps: expected an integer, got 'abc'"),
        ("gaussians.sh_degree=1.5", "gaussians.sh_degree: expected an integer, got 1.5"),
        ("threads=x", "threads: expected an integer or null, got 'x'"),
        ("background=[0,a,0]", "background[1]: expected a number, got 'a'"),
        ("scene.frozen_joints=3", "scene.frozen_joints: expected a list of strings, got 3"),
    ],
)
def test_a_mistyped_value_fails_at_composition_in_one_line(override: str, line: str) -> None:
    with pytest.raises(ConfigCompositionException) as info:
        _compose([override])
    assert isinstance(info.value.__cause__, ValidationError)
    assert composition_message(info.value) == line


def test_an_older_checkpoints_config_reads_with_the_schema_defaults() -> None:
    stored = read_checkpoint(DEMO)["hyper_parameters"]["cfg"]
    assert "execution" not in stored and "compile" in stored and "profile" in stored["scene"]  # older keys
    settings = training_settings(stored)
    assert isinstance(settings, Train) and settings.execution.kernels == "auto"  # filled from the schema
    assert settings.gaussians.num == stored["gaussians"]["num"] and settings.stages.stage1_steps == 1000
    assert settings.body is None and settings.deformer is None  # plugin-chosen groups: read from the config itself


def test_a_stored_config_of_the_wrong_type_is_refused() -> None:
    stored = read_checkpoint(DEMO)["hyper_parameters"]["cfg"]
    with pytest.raises(ValidationError):
        training_settings({**stored, "seed": "x"})


# keys whose schema default is deliberately not a group option's value: the old code's fallback for a stored config
# without the key (conf/gaussians/random.yaml steps SH every 500), or values each option sets (MISSING)
NOT_COMPARED = {"gaussians.sh_increase_every", "gaussians.num", "gaussians.sh_degree", "paths.output_dir"}


def _leaves(node, prefix: str = "") -> dict:
    out = {}
    for key, value in node.items():
        name = f"{prefix}{key}"
        out.update(_leaves(value, f"{name}.") if isinstance(value, dict) else {name: value})
    return out


def test_the_schema_defaults_are_train_yamls_values() -> None:
    """conf/train.yaml (and its default group options) state the defaults people read; the schema holds the same
    values for stored configs that lack a key. They must not drift apart."""
    cfg = _compose([])
    composed = OmegaConf.to_container(cfg, resolve=False)
    schema = OmegaConf.to_container(OmegaConf.structured(Train), resolve=False)
    groups = ("gaussians", "optim", "trainer", "callbacks", "paths")
    top = {
        k: v
        for k, v in schema.items()
        if k not in ("data", "body", "corrector", "deformer", "rasterizer", "loss", "densifier", "logger", "profile")
    }
    expected = {k: v for k, v in _leaves(top).items() if k not in NOT_COMPARED and k != "scene.thresholds"}
    found = _leaves({k: composed[k] for k in top})
    found["data_loader.num_workers"] = cfg.data_loader.num_workers  # ${oc.select:profile.loader_workers,0}
    assert {k: found.get(k) for k in expected} == expected
    assert set(groups) <= set(top)

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

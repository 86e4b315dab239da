"""Sweep configs compose: every job of a multirun sweep is a valid training config."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.types import RunMode

CONF = Path(__file__).resolve().parents[1] / "conf"
TABLE4 = [
    "paper_full",
    "simple_3dgs_lbs",
    "posenc_instead_of_latent",
    "foreground_only_loss",
    "all_sh_correction",
    "no_first_stage",
    "no_joint_optimisation",
    "no_boundary_mask",
    "no_corrector",
    "no_alpha_loss",
    "no_weight_std_loss",
]


def sweep_values(params: dict[str, str], key: str) -> list[str]:
    """The values a sweeper would launch for `key`, parsed by Hydra's own override grammar."""
    (override,) = OverridesParser.create().parse_overrides([f"{key}={params[key]}"])
    return [str(v) for v in override.sweep_string_iterator()]


def test_ablations_sweep_lists_every_table4_row() -> None:
    with initialize_config_module("framework.conf", version_base="1.3"):
        cfg = compose("ablations", return_hydra_config=True)
    assert cfg.hydra.mode == RunMode.MULTIRUN
    assert sweep_values(dict(cfg.hydra.sweeper.params), "+experiment") == TABLE4
    for name in TABLE4:
        assert (CONF / "experiment" / f"{name}.yaml").is_file(), f"sweep row {name} has no conf/experiment/{name}.yaml"


@pytest.mark.parametrize("experiment", TABLE4)
def test_each_ablation_job_composes(experiment: str) -> None:
    """What one job of the sweep gets: train.yaml, then the experiment appended (same as `+experiment=NAME`)."""
    with initialize_config_module("framework.conf", version_base="1.3"):
        job = compose("ablations", overrides=[f"+experiment={experiment}"])
        direct = compose("train", overrides=[f"+experiment={experiment}"])
    assert job == direct
    assert job.task_name == experiment

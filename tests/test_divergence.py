"""A training that goes wrong says so: a NaN injected into the loss or the gradients (tests/helpers/faults.py) stops
the run with one message naming the step, the term and the parameter groups, leaving the last good checkpoint on
disk; with divergence.action=rollback the run reloads that checkpoint, lowers the learning rates and finishes."""

from __future__ import annotations

import math

import pytest
import torch
from errors_table import check_documented, normalise
from test_training import _load, _run_dirs, _train

# the rows of docs/errors.md these tests check (test_bad_input.py checks that every row is tested)
DIVERGENCE_CASES = ("training_diverged_stop", "training_diverged_rollback")
FAULT = "`+loss.terms.fault={name: fault, at_step: 25, ...}` (tests/helpers/faults.py)"


def _all_finite(ckpt: dict) -> bool:
    return all(bool(torch.isfinite(v).all()) for v in ckpt["state_dict"].values() if v.is_floating_point())


# read before each update (a CPU's default), or after the step with the update skipped on the device (a GPU's; the
# verdict of step 25 is read during step 26 here, and the message must name step 25 all the same)
DEFERRED = pytest.mark.parametrize("deferred", ["false", "true"])


@DEFERRED
def test_nan_loss_stops_with_one_message_and_keeps_the_last_good_checkpoint(tmp_path, deferred):
    proc = _train(
        tmp_path,
        "trainer.max_steps=40",
        "+loss.terms.fault={name: fault, weight: 1.0, at_step: 25}",
        f"divergence.deferred={deferred}",
        faults={},
    )
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, proc.stderr[-3000:]
    assert "training diverged at step 25: non-finite loss term 'fault' = nan" in errors[0]
    ckpt_dir = _run_dirs(tmp_path)[-1] / "checkpoints"
    assert f"The last good checkpoint is {ckpt_dir / 'last.ckpt'}" in errors[0]
    check_documented(
        "training_diverged_stop", "train", f"a NaN loss at step 25: {FAULT}", normalise(errors[0], {"<tmp>": tmp_path})
    )
    last = _load(ckpt_dir / "last.ckpt")
    assert last["global_step"] == 20 and _all_finite(last)  # checkpoint_every=10: nothing written after the NaN
    assert not (ckpt_dir / "final.ckpt").exists() and not (_run_dirs(tmp_path)[-1] / "eval").exists()


@DEFERRED
def test_nan_gradient_rolls_back_lowers_the_learning_rates_and_finishes(tmp_path, deferred):
    proc = _train(
        tmp_path,
        "trainer.max_steps=40",
        "divergence.action=rollback",
        f"divergence.deferred={deferred}",
        "+loss.terms.fault={name: fault, weight: 1.0, at_step: 25, kind: nan_grad}",
        faults={},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    notes = [line for line in proc.stderr.splitlines() if "training diverged" in line]
    assert len(notes) == 1, proc.stderr[-3000:]
    assert "at step 25: non-finite gradient of parameter group 'means', 'quats', 'log_scales'" in notes[0]
    ckpt_dir = _run_dirs(tmp_path)[-1] / "checkpoints"
    assert f"rolled back to {ckpt_dir / 'last.ckpt'} (step 20) with learning rates x0.5 (rollback 1 of 3)" in notes[0]
    check_documented(
        "training_diverged_rollback",
        "train",
        f"a NaN gradient at step 25 with `divergence.action=rollback`: {FAULT}",
        normalise(notes[0], {"<tmp>": tmp_path}),
    )
    last = _load(ckpt_dir / "last.ckpt")
    assert last["global_step"] == 40 and _all_finite(last)
    assert last["splatrig_divergence"] == {"lr_scale": 0.5, "rollbacks": 1}
    groups = {g["name"]: g["lr"] for g in last["optimizer_states"][0]["param_groups"]}
    assert math.isclose(groups["opacity_logits"], 0.5 * 5.0e-2) and math.isclose(groups["sh0"], 0.5 * 2.5e-3)


def test_deferred_verdict_is_read_before_the_checkpoint_that_follows_it(tmp_path):
    """A NaN at step 29, the last before the checkpoint of step 30: the deferred form must read its verdict before that
    checkpoint is written (without the wait it would read it during step 30, with last.ckpt already at step 30)."""
    proc = _train(
        tmp_path,
        "trainer.max_steps=40",
        "divergence.deferred=true",
        "+loss.terms.fault={name: fault, weight: 1.0, at_step: 29}",
        faults={},
    )
    assert proc.returncode == 2, proc.stderr[-3000:]
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "training diverged at step 29: non-finite loss term 'fault' = nan" in errors[0]
    last = _load(_run_dirs(tmp_path)[-1] / "checkpoints" / "last.ckpt")
    assert last["global_step"] == 20 and _all_finite(last)

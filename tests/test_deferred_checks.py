"""Deferred divergence checks: a bad update is skipped on the device exactly (parameters, moments and step count as
before it; a good one equals a plain fused Adam step), the message equals the one `diagnose` reads from the tensors
themselves, and verdicts are read in order, never ahead of the steps they may read (`-m gpu` runs the same on CUDA,
where the read waits on an event)."""

from __future__ import annotations

import pytest
import torch

from framework.lightning.deferred_checks import DeferredChecks, defers
from framework.lightning.divergence import diagnose

NEEDS_CUDA = {"condition": not torch.cuda.is_available(), "reason": "needs a CUDA device"}
DEVICES = pytest.mark.parametrize(
    "device", ["cpu", pytest.param("cuda", marks=[pytest.mark.gpu, pytest.mark.skipif(**NEEDS_CUDA)])]
)


def _model(device: str, seed: int = 0) -> tuple[list[torch.nn.Parameter], torch.optim.Adam]:
    g = torch.Generator().manual_seed(seed)
    params = [torch.nn.Parameter(torch.randn(n, 3, generator=g).to(device)) for n in (5, 4, 2)]
    groups = [{"params": [params[0]], "name": "means"}, {"params": params[1:], "name": "networks"}]
    return params, torch.optim.Adam(groups, lr=0.1, eps=1e-15, fused=True)


def _backward(params: list[torch.nn.Parameter], poison: str | None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    terms = {"l1": sum((p**2).sum() for p in params), "ssim": params[0].abs().sum()}
    if poison == "term":
        terms["ssim"] = terms["ssim"] * float("nan")
    total = terms["l1"] + terms["ssim"]
    total.backward()
    if poison == "grad":
        params[2].grad[1, 0] = float("inf")
    if poison == "param":
        with torch.no_grad():
            params[0][0, 0] = float("nan")
    return total, terms


def _step(device: str, poison: str | None, deferred: bool) -> tuple[list[torch.Tensor], dict, str | None]:
    """Two good steps, then one with `poison`; the parameters and Adam state after it, and the message of its check."""
    params, opt = _model(device)
    checks = DeferredChecks()
    message = None
    for step in range(3):
        total, terms = _backward(params, poison if step == 2 else None)
        if deferred:
            opt.found_inf = checks.probe(step, total, terms, opt)
            opt.step()
            del opt.found_inf
            message = checks.first_bad()  # waits: every verdict up to this one
        elif step < 2:
            opt.step()
        else:  # the synchronous path's reference: read from the tensors themselves
            message = diagnose(step, total, {k: v.detach() for k, v in terms.items()}, opt)
        opt.zero_grad(set_to_none=True)
    state = {k: v.detach().cpu().clone() for p in params for k, v in opt.state[p].items()}
    return [p.detach().cpu().clone() for p in params], state, message


@DEVICES
@pytest.mark.parametrize("poison", ["term", "grad", "param"])
def test_bad_update_is_skipped_on_the_device_and_named_as_diagnose_names_it(device, poison):
    params, state, message = _step(device, poison, deferred=True)
    ref_params, ref_state, ref_message = _step(device, poison, deferred=False)  # skipped by not stepping at all
    assert message == ref_message and message.startswith("training diverged at step 2: non-finite")
    for p, r in zip(params, ref_params, strict=True):
        if poison == "param":  # the poisoned entry stays NaN (it was NaN before the skipped update too)
            assert torch.equal(p.isnan(), r.isnan())
            p, r = p.nan_to_num(), r.nan_to_num()
        assert torch.equal(p, r)
    assert state.keys() == ref_state.keys() and all(torch.equal(state[k], ref_state[k]) for k in state)


@DEVICES
def test_good_steps_equal_plain_fused_adam(device):
    """found_inf = 0 leaves fused Adam's arithmetic alone: three good steps, bit for bit."""
    params, state, message = _step(device, None, deferred=True)
    ref_params, ref_opt = _model(device)
    for _ in range(3):
        _backward(ref_params, None)
        ref_opt.step()
        ref_opt.zero_grad(set_to_none=True)
    assert message is None
    assert all(torch.equal(p, r.detach().cpu()) for p, r in zip(params, ref_params, strict=True))
    assert int(next(iter(ref_opt.state.values()))["step"]) == 3 and int(state["step"]) == 3


@DEVICES
def test_verdicts_are_read_in_order_and_not_ahead_of_their_steps(device):
    params, opt = _model(device)
    checks = DeferredChecks()
    for step, poison in enumerate([None, "term", None]):
        total, terms = _backward(params, poison)
        checks.probe(step, total, terms, opt)
        opt.zero_grad(set_to_none=True)
    assert checks.first_bad(before_step=0) is None and len(checks) == 3  # no verdict of step 0 or later yet
    if device == "cpu":  # on a CPU a verdict is ready at once (on a GPU, once its event has passed)
        assert checks.first_bad(before_step=1) is None and len(checks) == 2  # step 0 was good: read and gone
    message = checks.first_bad()
    assert message is not None and "at step 1: non-finite loss term 'ssim' = nan" in message
    assert len(checks) == 0  # step 2's verdict is dropped with the bad one: the stop or rollback discards it
    assert checks.first_bad() is None


def test_only_fused_adam_defers():
    params, fused = _model("cpu")
    assert defers(fused)
    assert not defers(torch.optim.Adam(params, lr=0.1, foreach=False))
    assert not defers(torch.optim.SGD(params, lr=0.1))


def test_config_decides_per_run_and_says_when_it_cannot():
    """`divergence.deferred`: auto defers on a GPU only (this CPU reads at once), true needs fused Adam."""
    from types import SimpleNamespace

    from framework.build import ConfigError
    from framework.config_schema import Divergence
    from framework.lightning.divergence import DivergencePolicy
    from framework.lightning.module import SplatModule

    params, fused = _model("cpu")
    unfused = torch.optim.Adam(params, lr=0.1, foreach=False)

    def decide(value, optimizer) -> bool:
        run = SimpleNamespace(divergence=DivergencePolicy.from_config(Divergence(deferred=value)), _defers_checks=None)
        return SplatModule._deferred(run, optimizer)

    assert decide("auto", fused) is False and decide(True, fused) is True and decide(False, fused) is False
    assert decide("auto", unfused) is False
    with pytest.raises(ConfigError, match=r"divergence.deferred=true: the optimizer does not run fused Adam"):
        decide(True, unfused)
    with pytest.raises(ValueError, match=r"divergence.deferred: expected true, false or auto, found 'maybe'"):
        DivergencePolicy.from_config(Divergence(deferred="maybe"))


def test_training_end_reads_what_is_pending():
    """A run stopped by its time limit can end on a step that reads no verdict: on_train_end reads them all."""
    from types import SimpleNamespace

    from framework.lightning.module import SplatModule

    params, opt = _model("cpu")
    total, terms = _backward(params, "grad")
    run = SimpleNamespace(_checks=DeferredChecks(), optimizers=lambda: SimpleNamespace(optimizer=opt), seen=[])
    run._checks.probe(7, total, terms, opt)
    run._diverged = lambda message, optimizer: run.seen.append((message, optimizer))
    SplatModule.on_train_end(run)
    assert run.seen == [(diagnose(7, total, terms, opt), opt)] and len(run._checks) == 0

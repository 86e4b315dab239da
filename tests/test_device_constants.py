"""Constants are copied to a device and dtype once and then reused (`framework.device_constants`): the values are the
constant's, a second request returns the same tensor, and a request for the constant's own device and dtype returns
the constant itself. (On a CPU the dtype is what changes; the device case is the same code.)"""

from __future__ import annotations

import torch

from framework.device_constants import constant_on, values_on


def test_constant_is_copied_once_per_dtype_and_never_for_its_own() -> None:
    constant = torch.tensor([-1.0, -0.5, 2.0])
    assert constant_on(constant, "cpu") is constant
    as64 = constant_on(constant, torch.device("cpu"), torch.float64)
    assert as64.dtype == torch.float64 and torch.equal(as64, constant.double())
    assert constant_on(constant, "cpu", torch.float64) is as64
    other = torch.tensor([-1.0, -0.5, 2.0])  # equal values, another constant: its own copy
    assert constant_on(other, "cpu", torch.float64) is not as64


def test_index_is_made_once() -> None:
    idx = values_on((3, 1, 2), torch.device("cpu"))
    assert idx.dtype == torch.long and idx.tolist() == [3, 1, 2]
    assert values_on((3, 1, 2), torch.device("cpu")) is idx
    size = values_on((64.0, 48.0), torch.device("cpu"), torch.float32)
    assert size.dtype == torch.float32 and size.tolist() == [64.0, 48.0]

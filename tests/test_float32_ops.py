"""The exactly rounded float32 emulation (`tests/helpers/float32_ops.py`) against numpy's float32 scalars, which
compute one IEEE operation at a time with no contraction: the same bits, so the emulation cannot depend on the CPU."""

from __future__ import annotations

import numpy as np
import torch

from tests.helpers import float32_ops as f32


def _float32_values(n: int, seed: int) -> np.ndarray:
    """float32 values over many binades and both signs, with the cancellations a determinant makes."""
    rng = np.random.default_rng(seed)
    return (rng.standard_normal(n) * np.exp(rng.uniform(-20, 20, n))).astype(np.float32)


def test_each_operation_rounds_as_float32_scalars():
    a, b = _float32_values(4000, 0), _float32_values(4000, 1)
    b[:1000] = a[:1000] * np.float32(1.0000001)  # nearly equal operands: subtraction cancels
    ta, tb = (torch.from_numpy(v.astype(np.float64)) for v in (a, b))
    with np.errstate(all="ignore"):
        expected = {"mul": a * b, "add": a + b, "sub": a - b, "div": a / b}
    for name, want in expected.items():
        got = getattr(f32, name)(ta, tb).numpy()
        assert np.array_equal(got.astype(np.float32), want, equal_nan=True), name
        assert np.array_equal(got, got.astype(np.float32).astype(np.float64)), f"{name}: not a float32 value"


def test_matmul_sums_left_to_right_like_glm():
    A = _float32_values(2 * 3 * 3, 2).reshape(2, 3, 3)
    B = _float32_values(2 * 3 * 2, 3).reshape(2, 3, 2)
    want = np.zeros((2, 3, 2), np.float32)
    for n in range(2):
        for i in range(3):
            for j in range(2):
                acc = A[n, i, 0] * B[n, 0, j]
                for k in (1, 2):
                    acc = np.float32(acc + np.float32(A[n, i, k] * B[n, k, j]))
                want[n, i, j] = acc
    got = f32.matmul(torch.from_numpy(A.astype(np.float64)), torch.from_numpy(B.astype(np.float64)))
    assert np.array_equal(got.numpy().astype(np.float32), want)

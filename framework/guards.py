"""Numeric guards: every clamp and epsilon that keeps the pipeline finite at its extremes, in one place.

Each number is a deliberate departure from exact math at a point where exact math has no finite answer (the log of a
zero stretch, a division by a zero norm, a rotation that a rank-deficient matrix does not determine). Each entry says
where it applies, what would happen without it and what it costs. The property tests (tests/test_numeric_*.py, and
the rasterizer extremes in framework/testing/conformance.py) check that at the extreme the clamp is exactly what
happens: the documented value, not a NaN and not some other number.

The rasterizer contract's own numbers (near and far planes, the alpha limits, the transmittance cut-off) are part of
its specification, not guards, and live in `framework.splat.contract`.
"""

from __future__ import annotations

# ---------------------------------------------------------------------------------------------- rotations, vectors
NORM_EPS = 1e-12
"""Vectors shorter than this normalise to a fixed default instead of dividing by ~0: a quaternion to the identity
rotation (`framework.geometry.quat_normalize`, and the JAX rasterizer on the squared norm), an SH direction to the
zero vector, leaving only the constant band (`framework.splat.sh.sh_basis`: the camera sits on the Gaussian's mean).
Cost: a Gaussian whose quaternion norm is below 1e-12 renders as axis-aligned."""

AXIS_ANGLE_TAYLOR_SQ = 1e-8
"""theta^2 below which Rodrigues' sin(t)/t and (1 - cos t)/t^2 switch to their Taylor series
(`framework.geometry.axis_angle_to_rotmat`): the closed forms lose every digit (and divide 0 by 0) at t = 0. The
truncation error of the series there is below 1e-17."""

# ------------------------------------------------------------------------------------------------------ skinning
LBS_MIN_STRETCH = 1e-4
"""Floor of the per-axis stretch k = a^T S a of a blended LBS transform before its log (`framework.rig.lbs`). A
degenerate blend (all weights zero, or a 50/50 blend of antipodal bone rotations, which is rank 1) has k = 0 along an
axis and log(0) = -inf; with the floor the posed scale shrinks by at most 1e4 (log-scale -9.21) and stays finite."""

WEIGHT_SUM_MIN = 1e-12
"""Floor of the sum of blend weights when they are renormalised to a partition of unity (`framework.rig.weight_field`
for both the grid and the surface weights): all-zero weights stay zero instead of becoming 0/0 = NaN."""

WEIGHT_PARTITION_TOL = 1e-5
"""A blend-weight volume whose nodes are non-negative and sum to 1 within this is a partition of unity
(`framework.rig.weight_field.WeightField`): its rows are renormalised once, in float64, and trilinear samples of it
(convex combinations of rows) need no per-lookup clamp or renormalisation. A volume beyond it is renormalised per
lookup, as any other. The grids `build_weight_grid` writes deviate by float32 rounding (about 1e-7)."""

WEIGHT_VAR_MIN = 1e-12
"""Variances of blend weights below this count as zero in the L_w standard deviation (`framework.rig.lbs.weight_std`):
sqrt has an infinite slope at 0, and rigid regions have a variance of exactly 0. The std of a variance below 1e-12 is
below 1e-6, so the term loses at most 1e-6 per joint."""

WEIGHT_FIELD_NAN_NODE = 0.0
"""Grid coordinate (in nodes) that a NaN point coordinate is looked up at by the blend-weight field's corner gather
(`framework.rig.weight_field.WeightField.sample`): NaN would otherwise become an undefined integer index (an
IndexError on CPU, a device-side assert on CUDA). The weights stay finite with zero gradient along that axis; the
NaN itself still reaches the loss through the Gaussian's mean, where the divergence guard names it."""

# ------------------------------------------------------------------------------------------- polar decomposition
POLAR_TIKHONOV = 1e-3
"""Relative Tikhonov damping d = 1e-3 tr(S) of the 3x3 solve in the closed-form backward of the polar rotation
(`framework.rig.polar`). Where A is rank-deficient the rotation is not determined and the exact gradient is infinite;
damped, its norm is at most |g| / (2 d). Elsewhere the bias is ~ (d / (s_i + s_j))^2 for singular values s."""

POLAR_DAMPING_FLOOR = 1e-30
"""Absolute floor of d^2 in the same solve, for A = 0 (all blend weights zero), where tr(S) = 0: the gradient is 0."""

POLAR_SINGULAR_TOL = 1e-6
"""det(A) / (|A|_F / sqrt 3)^3 below this sends a matrix from Higham's Newton iteration (which needs A^-1) to the
float64 SVD path of `polar_rotation_values(method="newton")`; both give the same values where both apply."""

HIDDEN_OPACITY_LOGIT = -1e4
"""Opacity logit that hides a Gaussian while a compaction step tries removing it (`framework.compaction.pruning.
prune_within_tolerance`): sigmoid(-1e4) is exactly 0 in float32, below the rasterizers' 1/255 alpha cull, so the
render equals the one without the Gaussian; finite, so a corrector's added logit cannot make inf - inf."""

# -------------------------------------------------------------------------------------------------------- metrics
PSNR_MSE_FLOOR = 1e-10
"""Floor of the mean squared error in PSNR: identical images score 100 dB instead of inf, so averages over frames
and logged training curves stay finite (`plugins/metric/psnr.py`, `framework.lightning.module.psnr`)."""

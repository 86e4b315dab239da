"""The MLP behind the appearance correctors (the paper's F_a), shared by `latent` and `posenc`.

F_a maps [pose, per-Gaussian feature] to residuals (d_alpha, d_s, d_r, d_SH). The pose is the same for all N Gaussians
of a frame, so the first layer is split: W [pose, f] = W_p pose + W_f f, and W_p pose (one vector) is computed once
and broadcast instead of concatenating an [N, P] copy of the pose. The last layer starts at zero, so a freshly
switched-on corrector is exactly the identity and stage 2 starts from the stage-1 solution.

`active_rows` (empty: every Gaussian) restricts the MLP to the Gaussians whose correction still depends on the pose;
the others carry their (constant) correction in their own parameters and get none here. It is set by a partial fold
(`framework.compaction.corrector_fold`) of a compact model and saved with the weights, so a novel pose pays for the
MLP on those rows only.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from framework.device_constants import constant_on
from framework.execution import Execution
from framework.geometry import IDENTITY_QUAT, quat_multiply
from framework.interfaces.corrector import Corrector
from framework.types import Gaussians, num_sh_coeffs


def _fuses_layers(x: Tensor, execution: Execution) -> bool:
    """Whether F_a runs its layers through oneDNN's fused linear (`torch.ops.mkldnn._linear_pointwise`): without
    gradients (that op has no backward), on CPU float32 that `execution` runs in the CPU's own forms, where the build
    has it.

    Why: a novel-pose frame on the CPU pays F_a in full, and there the plain layers cost more than their products. The
    bias is copied into each [M, 128] output before the product, the ReLU is a second pass over it, and the 11-wide
    head ran at a third of the wide layers' rate: 0.37 against 0.16 ms per call on 6k rows, and 1.17 against 1.06 ms
    for a 128-wide layer with its ReLU (2-core AVX-512 VM, medians). The values agree with the plain layers' to
    float32 rounding."""
    return (
        not torch.is_grad_enabled()
        and execution.compiled(x)  # a CPU tensor, and not the torch execution (a GPU's code on a CPU)
        and x.dtype == torch.float32
        and _FUSED_LINEAR_AVAILABLE
    )


def _has_fused_linear() -> bool:
    try:
        return torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_linear_pointwise")
    except (AttributeError, RuntimeError):
        return False


_FUSED_LINEAR_AVAILABLE = _has_fused_linear()


class MLPCorrector(Corrector):
    """Base class: subclasses say how to build the per-Gaussian feature [N, F] (`features`, `feature_dim`)."""

    feature_dim: int = 0

    def __init__(self, hidden: int = 128, layers: int = 4, all_sh: bool = False, sh_degree: int = 3) -> None:
        super().__init__()
        if layers < 2:
            raise ValueError(f"corrector.layers: expected >= 2 linear layers, got {layers}.")
        if not 0 <= sh_degree <= 3:
            raise ValueError(f"corrector.sh_degree: expected 0..3, got {sh_degree}.")
        self.hidden, self.num_layers, self.all_sh, self.sh_degree = hidden, layers, all_sh, sh_degree
        self.num_pose_features: int | None = None
        self.pose_in: nn.Linear | None = None
        self.feature_in: nn.Linear | None = None
        self.trunk: nn.Sequential | None = None
        self.head: nn.Linear | None = None
        self.register_buffer("active_rows", torch.zeros(0, dtype=torch.long))  # [M] (empty: all rows)

    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ) -> None:
        """A stored `active_rows` may have any length; checkpoints written before it existed have none (all rows)."""
        key = prefix + "active_rows"
        if key in state_dict:
            self.active_rows = torch.empty_like(state_dict[key], device=self.active_rows.device)
        else:
            self.active_rows = self.active_rows.new_zeros(0)
        first = len(missing_keys)
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )
        if key in missing_keys[first:]:
            missing_keys.remove(key)

    def corrected_rows(self) -> Tensor:
        return self.active_rows

    def set_corrected_rows(self, rows: Tensor) -> None:
        self.active_rows = rows

    @property
    def num_sh_out(self) -> int:
        """SH coefficients corrected: all of degree <= sh_degree (all_sh) or the DC term only."""
        return num_sh_coeffs(self.sh_degree) if self.all_sh else 1

    def bind(self, num_pose_features: int) -> None:
        """Build the layers for a body with `num_pose_features` pose inputs (`body.num_pose_features`)."""
        if num_pose_features < 1:
            raise ValueError(f"corrector.bind: num_pose_features must be positive, got {num_pose_features}.")
        self.num_pose_features = num_pose_features
        self.pose_in = nn.Linear(num_pose_features, self.hidden, bias=False)
        self.feature_in = nn.Linear(self.feature_dim, self.hidden)
        trunk: list[nn.Module] = []
        for _ in range(self.num_layers - 2):
            # in place: the activation overwrites the product it follows (whose backward does not read it), so no
            # [N, H] temporary is allocated per layer
            trunk += [nn.Linear(self.hidden, self.hidden), nn.ReLU(inplace=True)]
        self.trunk = nn.Sequential(*trunk)
        self.head = nn.Linear(self.hidden, 1 + 3 + 4 + 3 * self.num_sh_out)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def features(self, gaussians: Gaussians) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def residuals(self, gaussians: Gaussians, pose: Tensor) -> Tensor:
        """[N, 11] (or [N, 8 + 3K] with all_sh): d_alpha, d_s (3), d_r (4, added to the identity), d_SH (3 or 3K)."""
        if self.head is None:
            raise RuntimeError(
                f"corrector '{self.registry_name}': bind(num_pose_features) was not called; call it with the body's "
                "pose size (body.num_pose_features) before the first forward."
            )
        pose = pose.detach().reshape(-1)  # gradient-stopped: appearance must not bend the pose
        if pose.shape[0] != self.num_pose_features:
            raise ValueError(
                f"corrector '{self.registry_name}': pose has {pose.shape[0]} features but the corrector was bound "
                f"with {self.num_pose_features}; bind it to the body the poses come from."
            )
        f = self.features(gaussians)  # [N, F]
        rows = self.active_rows
        if rows.numel():
            if int(rows[-1]) >= f.shape[0]:
                raise ValueError(
                    f"corrector '{self.registry_name}': it corrects Gaussian rows up to {int(rows[-1])} but got "
                    f"{f.shape[0]} Gaussians; a partially folded corrector belongs to the Gaussians it was folded "
                    "with (prune the model before folding, not after)."
                )
            f = f.index_select(0, rows)  # [M, F]
        pose_h = self.pose_in(pose.to(f.dtype))  # [H]
        if _fuses_layers(f, self.execution):
            out = self._mlp_fused(f, pose_h)
        else:
            h = self.feature_in(f) + pose_h  # [M, H]
            h = self.trunk(torch.relu_(h))
            out = self.head(h)  # [M, out]
        if not rows.numel():
            return out
        return out.new_zeros(gaussians.num, out.shape[1]).index_copy(0, rows, out)  # [N, out], 0 where folded

    def _mlp_fused(self, f: Tensor, pose_h: Tensor) -> Tensor:
        """The MLP on [M, F] features through oneDNN's linear layer with its bias and ReLU in the same call
        (`_fuses_layers`)."""
        linear = torch.ops.mkldnn._linear_pointwise
        h = linear(f, self.feature_in.weight, self.feature_in.bias + pose_h, "relu", [], "")  # [M, H]
        for layer in self.trunk[::2]:  # Linear, ReLU, Linear, ReLU, ...
            h = linear(h, layer.weight, layer.bias, "relu", [], "")
        return linear(h, self.head.weight, self.head.bias, "none", [], "")  # [M, out]

    def forward(self, gaussians: Gaussians, pose: Tensor) -> Gaussians:
        if not self.enabled:
            return gaussians
        d = self.residuals(gaussians, pose).to(gaussians.means.dtype)
        n = gaussians.num
        d_rot = d[:, 4:8] + constant_on(IDENTITY_QUAT, d.device, d.dtype)  # the rotation residual is added to it
        d_sh = d[:, 8:].reshape(n, self.num_sh_out, 3)
        sh = gaussians.sh
        k = min(sh.shape[1], self.num_sh_out)
        sh = torch.cat([sh[:, :k] + d_sh[:, :k].to(sh.dtype), sh[:, k:]], dim=1)
        return gaussians.replace(
            opacity_logits=gaussians.opacity_logits + d[:, 0],
            log_scales=gaussians.log_scales + d[:, 1:4],
            quats=quat_multiply(d_rot, gaussians.quats, execution=self.execution),
            sh=sh,
        )

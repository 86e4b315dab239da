"""The LBS deformer shared by the `lbs` and `lbs_residual` plugins: weights from the blend-weight field (or baked per
Gaussian), the L_w sampling points, then `framework.rig.lbs` (the SH rotation deferred to the renderer on request).
It holds state (the bound field), so it lives with the model rather than with the stateless rig math."""

from __future__ import annotations

import torch
from torch import Tensor

from framework.interfaces.body import BodyModel
from framework.interfaces.deformer import Deformer, DeformOutput
from framework.rig.fold import fold_weights
from framework.rig.lbs import CENTRE_MODES, POLAR_DTYPES, STRETCH_MODES, lbs_with_sh_frames, six_points, weight_std
from framework.rig.sh_rotation import rotate_sh
from framework.rig.weight_field import WeightField, build_weight_grid
from framework.types import Gaussians


class LBSDeformerBase(Deformer):
    """Shared by the `lbs` and `lbs_residual` deformers (registered in plugins/deformer/).

    Weights: the Gaussians' baked `skin_weights` when present, else the weight field at the canonical means.

    aux["weight_std"] [N] is the L_w term (std of the weights over the six points x +- s_l a_l); it is computed only
    when gradients are enabled (training), `weight_std` is on and a loss term reads it (`use_aux`), and is zero for
    baked weights (nothing to smooth). On a body with frozen joints (`BodyModel.unfolded_skinning`) it is measured
    over the whole skeleton, as without freezing: the six points' weights from a second field over every joint of the
    full skeleton (the LBS field is its folded sums), plus the change F_dw makes on the kept joints. `centres` chooses
    how centres move (`framework.rig.lbs.apply_lbs`).

    Where the execution (`framework.execution`) compiles the tensors (CPU float32/float64 under the compiled kernels):
    `compiled_weights` runs the seven points' lookup, F_dw's combination and L_w as compiled loops
    (`framework.kernels.skin_weights`; the same values, to float32 rounding), and `bake` stores what they give;
    `compiled_skinning` runs everything of a training step's LBS after the blend's matrix product (the polar
    decomposition, the quaternions, centres and stretch) as compiled loops with a hand-written backward
    (`framework.kernels.skinning.lbs_with_sh_frames_trainable`; float64 inside, so the polar iteration is float64
    whatever `polar_dtype` says); and baked weights without gradients (inference) are skinned by the same kernels
    (`lbs_with_sh_frames_compiled`: the same values in float64, cast back), whatever the rasterizer.
    """

    def __init__(
        self,
        grid_resolution: int = 64,
        stretch: str = "diag",
        weight_std: bool = True,
        use_cache: bool = True,
        polar_dtype: str = "float32",
        centres: str = "blended",
        compiled_weights: bool = True,
        compiled_skinning: bool = True,
    ) -> None:
        super().__init__()
        if stretch not in STRETCH_MODES:
            raise ValueError(f"deformer.stretch: expected one of {STRETCH_MODES}, got '{stretch}'.")
        if polar_dtype not in POLAR_DTYPES:
            raise ValueError(f"deformer.polar_dtype: expected one of {sorted(POLAR_DTYPES)}, got '{polar_dtype}'.")
        if centres not in CENTRE_MODES:
            raise ValueError(f"deformer.centres: expected one of {CENTRE_MODES}, got '{centres}'.")
        self.polar_dtype = POLAR_DTYPES[polar_dtype]
        self.grid_resolution, self.stretch, self.centres = grid_resolution, stretch, centres
        self.weight_std_enabled, self.use_cache = weight_std, use_cache
        self.compiled_weights, self.compiled_skinning = compiled_weights, compiled_skinning
        self.report_weight_std = weight_std
        self.field: WeightField | None = None
        self.unfolded: WeightField | None = None  # frozen joints: the field over the full skeleton, for L_w only

    def bind(self, body: BodyModel | None, bounds: Tensor | None) -> None:
        if body is None or bounds is None:
            raise ValueError(
                f"deformer '{self.registry_name}' needs a body model and a canonical box; for static scenes use "
                "deformer=identity."
            )
        unfolded = body.unfolded_skinning()
        self.unfolded = None
        if unfolded is None:
            self.field = WeightField.from_body(body, bounds, self.grid_resolution, self.use_cache)
            return
        # Frozen joints: one grid over every joint of the full skeleton (one closest-point pass), and the LBS field
        # as its folded sums (exactly the grid of the folded weights: both are linear in the vertex weights).
        weights, fold_index = unfolded
        full = build_weight_grid(body.rest_vertices, body.faces, weights, bounds, self.grid_resolution, self.use_cache)
        folded = fold_weights(full.movedim(0, -1), fold_index.cpu(), int(body.num_joints)).movedim(-1, 0)
        box = torch.as_tensor(bounds, dtype=torch.float32)
        self.field = WeightField(folded.contiguous(), box)
        self.unfolded = WeightField(full, box)
        self.register_buffer("fold_index", fold_index.clone(), persistent=False)  # [J_full] -> kept joint
        shared = torch.bincount(fold_index, minlength=self.field.num_joints) > 1  # [J] kept joints that fold others
        self.register_buffer("fold_groups", torch.nonzero(shared).squeeze(-1), persistent=False)  # [G]
        self.register_buffer("fold_members", torch.nonzero(shared[fold_index]).squeeze(-1), persistent=False)  # [M]

    def use_aux(self, keys: frozenset[str]) -> None:
        self.report_weight_std = self.weight_std_enabled and "weight_std" in keys

    def weights(self, points: Tensor) -> Tensor:
        """Blend weights [..., J] at canonical points [..., 3]."""
        if self.field is None:
            raise RuntimeError(f"deformer '{self.registry_name}': call bind(body, bounds) before using it.")
        return self.refine(points, self.field.sample(points))

    def refine(self, points: Tensor, grid_weights: Tensor) -> Tensor:
        """The weights the model uses from the grid's [..., J] at `points` (`lbs_residual` adds F_dw here)."""
        return grid_weights

    def residual(self, points: Tensor) -> tuple[str, Tensor | None]:
        """How `refine` changes the grid weights at `points` [..., 3]: (combination, F_dw's residual [..., J]), one of
        the combinations of `framework.kernels.skin_weights.COMBINE_MODES`; ("none", None) without F_dw."""
        return "none", None

    @property
    def residual_eps(self) -> float:
        """The floor added to the grid weights before their log (the softmax combination)."""
        return 0.0

    @property
    def refines(self) -> bool:
        """Whether `refine` changes the grid weights now (F_dw switched on)."""
        return False

    def smooth_weights(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """points [N, 7, 3] (the centre, then the six L_w points) -> (weights [N, J] at the centres, L_w [N])."""
        if self.unfolded is None:
            if self._weights_compiled(points):
                from framework.kernels.skin_weights import smooth_weights_compiled  # imports numba: first use only

                combine, dw = self.residual(points)  # dw [N, 7, J] or None
                return smooth_weights_compiled(self.field, points, dw, combine, self.residual_eps)
            w7 = self.weights(points)  # [N, 7, J]
            return w7[:, 0], weight_std(w7[:, 1:])
        full7 = self.unfolded.sample(points)  # [N, 7, J_full]: one lookup for all seven points
        if not self.refines:
            return fold_weights(full7[:, 0], self.fold_index, self.field.num_joints), weight_std(full7[:, 1:])
        grid7 = fold_weights(full7, self.fold_index, self.field.num_joints)  # [N, 7, J]
        w7 = self.refine(points, grid7)
        # L_w = std(full) + (std(w) - std(grid)): the whole skeleton's spread plus the change F_dw makes on the kept
        # joints. A kept joint that folds no other joint is the same column in `full` and `grid`, so its two terms
        # cancel exactly: only the joints of the folded groups enter the difference (the same value, fewer columns).
        folded_groups = weight_std(full7[:, 1:, self.fold_members]) - weight_std(grid7[:, 1:, self.fold_groups])
        return w7[:, 0], weight_std(w7[:, 1:]) + folded_groups

    def _weights_compiled(self, points: Tensor) -> bool:
        """Whether `smooth_weights` takes the compiled loops: switched on, compiled by the execution, a
        partition-of-unity grid (the only kind `framework.rig.weight_field` builds from a body; other grids are
        clamped and renormalised)."""
        return self.compiled_weights and self.execution.compiled(points) and self.field.partition_of_unity

    def _skins_compiled(self, gaussians: Gaussians, w: Tensor, bone_transforms: Tensor) -> bool:
        """Whether this call takes the compiled skinning without gradients: baked weights that the execution
        compiles, no gradient asked (inference)."""
        if gaussians.skin_weights is None or not self.execution.compiled(w):
            return False
        tensors = (gaussians.means, gaussians.quats, gaussians.log_scales, w, bone_transforms)
        return not (torch.is_grad_enabled() and any(t.requires_grad for t in tensors))

    def _skins_compiled_with_grad(self, gaussians: Gaussians, w: Tensor, bone_transforms: Tensor) -> bool:
        """Whether this call takes the compiled skinning with gradients (training): switched on, every tensor
        compiled by the execution."""
        tensors = (gaussians.means, gaussians.quats, gaussians.log_scales, w, bone_transforms)
        return (
            self.compiled_skinning
            and self.execution.compiled(*tensors)
            and torch.is_grad_enabled()
            and any(t.requires_grad for t in tensors)
        )

    @torch.no_grad()
    def bake(self, gaussians: Gaussians) -> Tensor:
        """The weights this deformer uses for each Gaussian, [N, J], to store as `skin_weights` for inference.

        When training computes them compiled, so does the bake (the centre repeated as all seven points), so a baked
        model deforms exactly as the trained one did, not within float32 rounding of it."""
        means = gaussians.means
        if self.field is not None and self.unfolded is None and self._weights_compiled(means):
            return self.smooth_weights(means.unsqueeze(-2).expand(-1, 7, -1))[0].detach().clone()
        return self.weights(means).detach().clone()

    @torch.no_grad()
    def rebuilds_weights(self, means: Tensor, weights: Tensor) -> bool:
        """True when `weights` are the bound field's at `means` (no F_dw in them): binding the field rebuilds them."""
        if self.field is None:
            return False
        return torch.allclose(self.weights(means), weights, rtol=0.0, atol=1e-6)  # the same lookup, to rounding

    def forward(self, gaussians: Gaussians, bone_transforms: Tensor | None, defer_sh: bool = False) -> DeformOutput:
        if bone_transforms is None:
            raise ValueError(f"deformer '{self.registry_name}' needs bone_transforms [J, 4, 4]; got None.")
        aux: dict[str, Tensor] = {}
        if gaussians.skin_weights is not None:
            w = gaussians.skin_weights
            aux["weight_std"] = w.new_zeros(gaussians.num)
        elif self.report_weight_std and torch.is_grad_enabled():
            # one lookup for the centre and the six L_w points: the field (and F_dw) cost is per call, then per point
            centre = gaussians.means.unsqueeze(-2)  # [N, 1, 3]
            points = torch.cat([centre, six_points(gaussians, self.execution)], dim=-2)  # [N, 7, 3]
            w, aux["weight_std"] = self.smooth_weights(points)  # [N, J], [N]
        else:
            w = self.weights(gaussians.means)  # [N, J]
        if self._skins_compiled(gaussians, w, bone_transforms):
            from framework.kernels.skinning import lbs_with_sh_frames_compiled  # imports numba: first use only

            posed, R = lbs_with_sh_frames_compiled(gaussians, w, bone_transforms, self.stretch, self.centres)
        elif self._skins_compiled_with_grad(gaussians, w, bone_transforms):
            from framework.kernels.skinning import lbs_with_sh_frames_trainable  # imports numba: first use only

            posed, R = lbs_with_sh_frames_trainable(gaussians, w, bone_transforms, self.stretch, self.centres)
        else:
            posed, R = lbs_with_sh_frames(
                gaussians, w, bone_transforms, self.stretch, self.polar_dtype, self.centres, self.execution
            )
        if posed.sh.shape[1] == 1:  # degree 0 does not turn
            return DeformOutput(posed=posed, weights=w, aux=aux)
        if defer_sh:
            return DeformOutput(posed=posed, weights=w, aux=aux, sh_frames=R)
        return DeformOutput(posed=posed.replace(sh=rotate_sh(posed.sh, R, self.execution)), weights=w, aux=aux)

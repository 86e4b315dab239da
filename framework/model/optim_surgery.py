"""Change the number of Gaussians N while keeping optimizer state aligned with the rows it belongs to.

Densification replaces each per-Gaussian `nn.Parameter` by a new one with more or fewer rows. The optimizer keys its
state by the parameter object, so the new parameter must take the old one's place in its param group and its state
tensors (Adam's exp_avg / exp_avg_sq, amsgrad's max_exp_avg_sq, ...) must be cut the same way: kept rows keep their
moments, new rows start at zero. Scalar state (Adam's step) is kept as is.

Works with any layout of optimizers, found by parameter identity:
  * `dict[str, Optimizer]`, one optimizer per key (gsplat's convention), or several keys sharing one optimizer;
  * a single `Optimizer` holding every parameter, one named param group per key (`group["name"]`) or any grouping;
  * Lightning's `LightningOptimizer` wrappers (unwrapped).
`params` may be a plain dict or an `nn.ParameterDict`; entries are replaced in place (`params[name] = new`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, MutableMapping
from typing import Any

import torch
from torch import Tensor, nn

Optimizers = torch.optim.Optimizer | MutableMapping[str, torch.optim.Optimizer] | Iterable[torch.optim.Optimizer] | None
ParamFn = Callable[[str, Tensor], Tensor]  # (name, old values) -> new values
StateFn = Callable[[str, Tensor], Tensor]  # (state key, old per-row state) -> new per-row state


def _unwrap(opt: Any) -> torch.optim.Optimizer:
    inner = getattr(opt, "_optimizer", None)  # LightningOptimizer shares state with the optimizer it wraps
    return inner if isinstance(inner, torch.optim.Optimizer) else opt


def optimizer_list(optimizers: Optimizers) -> list[torch.optim.Optimizer]:
    """The distinct optimizers, whatever container holds them."""
    if optimizers is None:
        return []
    if isinstance(optimizers, torch.optim.Optimizer) or hasattr(optimizers, "param_groups"):
        items = [optimizers]
    elif isinstance(optimizers, MutableMapping):
        items = list(optimizers.values())
    else:
        items = list(optimizers)
    out: list[torch.optim.Optimizer] = []
    for opt in map(_unwrap, items):
        if not any(opt is o for o in out):
            out.append(opt)
    return out


def num_rows(params: MutableMapping[str, Tensor]) -> int:
    """N, checked to be the same for every entry (dim 0)."""
    sizes = {name: p.shape[0] if p.dim() > 0 else -1 for name, p in params.items()}
    distinct = set(sizes.values())
    if len(distinct) > 1 or -1 in distinct:
        raise ValueError(
            f"per-Gaussian params must all have the same leading dimension N; found {sizes}. Pass only per-Gaussian "
            f"parameters (networks and per-frame parameters belong elsewhere)."
        )
    return distinct.pop() if distinct else 0


@torch.no_grad()
def update_params(
    params: MutableMapping[str, Tensor],
    optimizers: Optimizers,
    param_fn: ParamFn,
    state_fn: StateFn,
    names: Iterable[str] | None = None,
) -> None:
    """Replace `params[name]` by `param_fn(name, old)` for each name, and each per-row optimizer state by
    `state_fn(key, old_state)`. The new parameter takes the old one's slot in its param group."""
    opts = optimizer_list(optimizers)
    for name in list(params.keys()) if names is None else list(names):
        old = params[name]
        new = nn.Parameter(param_fn(name, old.detach()).contiguous(), requires_grad=old.requires_grad)
        params[name] = new
        n_old = old.shape[0] if old.dim() > 0 else None
        found = False
        for opt in opts:
            for group in opt.param_groups:
                for i, p in enumerate(group["params"]):
                    if p is not old:
                        continue
                    found = True
                    group["params"][i] = new
                    state = opt.state.pop(old, None)
                    if state is not None:
                        opt.state[new] = {
                            k: state_fn(k, v) if _is_row_state(v, old, n_old) else v for k, v in state.items()
                        }
        if not found and old.requires_grad and opts:
            raise ValueError(
                f"parameter '{name}' requires grad but no optimizer holds it; add it to an optimizer (one param group "
                f"per per-Gaussian parameter) or set requires_grad=False."
            )


def _is_row_state(v: Any, param: Tensor, n: int | None) -> bool:
    return isinstance(v, Tensor) and n is not None and v.dim() > 0 and v.shape[0] == n and v.shape == param.shape


def keep_rows(params: MutableMapping[str, Tensor], optimizers: Optimizers, keep: Tensor) -> None:
    """Keep the rows selected by `keep` (bool mask [N] or index [M]), with their optimizer state (prune)."""
    keep = _as_index(keep)
    update_params(params, optimizers, lambda _n, p: p[keep], lambda _k, v: v[keep])


def append_rows(params: MutableMapping[str, Tensor], optimizers: Optimizers, new: MutableMapping[str, Tensor]) -> None:
    """Append rows `new[name]` ([M, ...] for every name in params); their optimizer state starts at zero."""
    missing = set(params) - set(new)
    if missing:
        raise ValueError(f"append_rows: new rows missing for {sorted(missing)}; every per-Gaussian key needs them.")
    counts = {name: v.shape[0] for name, v in new.items() if name in params}
    if len(set(counts.values())) > 1:
        raise ValueError(f"append_rows: new rows differ in count between keys: {counts}.")
    m = next(iter(counts.values()), 0)

    def param_fn(name: str, p: Tensor) -> Tensor:
        return torch.cat([p, new[name].to(p.device, p.dtype)])

    def state_fn(_key: str, v: Tensor) -> Tensor:
        return torch.cat([v, v.new_zeros((m, *v.shape[1:]))])

    update_params(params, optimizers, param_fn, state_fn)


def replace_values(
    params: MutableMapping[str, Tensor], optimizers: Optimizers, name: str, values: Tensor, reset_state: bool = True
) -> None:
    """Overwrite one parameter's values (same shape); its optimizer moments restart at zero when `reset_state`
    (what 3DGS does on an opacity reset, so stale momentum does not undo the reset)."""
    update_params(
        params,
        optimizers,
        lambda _n, p: values.to(p.device, p.dtype),
        (lambda _k, v: torch.zeros_like(v)) if reset_state else (lambda _k, v: v),
        names=[name],
    )


def _as_index(sel: Tensor) -> Tensor:
    return torch.nonzero(sel, as_tuple=False).flatten() if sel.dtype == torch.bool else sel.long()

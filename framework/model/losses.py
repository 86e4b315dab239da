"""The weighted sum of loss terms a config asks for.

A loss config is a `terms` mapping, one entry per term:

    terms:
      l1: {weight: 0.8, boundary: true}     # key = registry name; other keys = constructor kwargs
      lpips: {weight: 0.0}                  # weight 0: never built (LPIPS would load a network for nothing)
      l1_fg: {name: l1, weight: 0.1, foreground_only: true}   # `name:` lets one term appear twice

Every term returns its unweighted value; the composite returns the weighted total and the unweighted values (detached)
so each term is logged on its own scale.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from torch import Tensor, nn

from framework.execution import COMPILED, Execution
from framework.types import FrameBatch, RenderOutput


class CompositeLoss(nn.Module):
    """The terms of a loss config, each built with the model's execution (`framework.execution`)."""

    def __init__(self, terms: Mapping[str, Mapping[str, Any]], execution: Execution = COMPILED) -> None:
        super().__init__()
        from framework.plugins import load_plugins
        from framework.registry import LOSSES

        load_plugins()
        self.weights: dict[str, float] = {}
        self.terms = nn.ModuleDict()
        for key, spec in (terms or {}).items():
            if not isinstance(spec, Mapping):
                raise ValueError(
                    f"loss config: terms.{key} must be a mapping like {{weight: 0.8}}, found {spec!r}. "
                    f"Write `{key}: {{weight: <float>}}`."
                )
            kwargs = dict(spec)
            if "weight" not in kwargs:
                raise ValueError(f"loss config: terms.{key} has no 'weight'; add `weight: <float>` (0 disables it).")
            weight = float(kwargs.pop("weight"))
            name = str(kwargs.pop("name", key))
            if weight == 0.0:
                continue
            self.terms[key] = LOSSES.build(name, **kwargs)
            self.terms[key].set_execution(execution)
            self.weights[key] = weight

    @property
    def aux_keys(self) -> frozenset[str]:
        """Deformer aux outputs the built terms read (a term with weight 0 is not built, so it asks for nothing)."""
        return frozenset(k for term in self.terms.values() for k in term.aux_keys)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], execution: Execution = COMPILED) -> CompositeLoss:
        """Build from a loss group config (`{terms: {...}}`)."""
        if "terms" not in cfg:
            raise ValueError(f"loss config: expected a 'terms' mapping, found keys {sorted(cfg)}. See conf/loss/.")
        return cls(cfg["terms"], execution)

    def forward(
        self, render: RenderOutput, batch: FrameBatch, aux: dict[str, Tensor] | None = None
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """(weighted total, {term: unweighted value, detached})."""
        aux = aux or {}
        total = render.rgb.new_zeros(())
        values: dict[str, Tensor] = {}
        for key, term in self.terms.items():
            value = term(render, batch, aux)
            total = total + self.weights[key] * value
            values[key] = value.detach()
        return total, values

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={w:g}" for k, w in self.weights.items()) or "(no terms)"

"""Pareto fronts: which points no other point beats on every objective at once."""

from __future__ import annotations

import math
from collections.abc import Sequence


def dominates(a: Sequence[float], b: Sequence[float]) -> bool:
    """a is at least as good as b everywhere and better somewhere (every objective maximised)."""
    return all(x >= y for x, y in zip(a, b, strict=True)) and any(x > y for x, y in zip(a, b, strict=True))


def pareto_front(points: Sequence[Sequence[float]], maximise: Sequence[bool]) -> list[bool]:
    """For each point, whether it is on the Pareto front: no other point dominates it (objectives with
    `maximise[k]` False are minimised). Equal points do not dominate each other, so ties are on the front together.
    A point with a missing (NaN) objective is compared on nothing and is never on the front.

    Simple cull: sorted best-first in lexicographic order, a point can only be dominated by one before it, and, since
    dominance is transitive, by one already on the front; so each point is checked against the front only.
    """
    signs = [1.0 if m else -1.0 for m in maximise]
    oriented = [tuple(s * float(v) for s, v in zip(signs, p, strict=True)) for p in points]
    on_front = [False] * len(points)
    front: list[tuple[float, ...]] = []
    order = sorted(
        (i for i, p in enumerate(oriented) if not any(math.isnan(v) for v in p)),
        key=lambda i: oriented[i],
        reverse=True,
    )
    for i in order:
        if not any(dominates(f, oriented[i]) for f in front):
            front.append(oriented[i])
            on_front[i] = True
    return on_front

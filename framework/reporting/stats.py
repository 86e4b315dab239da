"""Seed statistics: mean and spread of a cell, a difference between two cells and its noise, and the verdict that
compares our difference with the paper's (or, for a row the paper does not have, with no change)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

AGREES, DISAGREES, WITHIN_NOISE, TOO_FEW = "agrees", "disagrees", "within noise", "needs 2 seeds"
BETTER, WORSE = "better", "worse"


@dataclass(frozen=True)
class Spread:
    mean: float
    std: float  # sample standard deviation over seeds (n - 1 in the denominator); NaN for one seed
    n: int


def spread(values: Iterable[float | None]) -> Spread:
    """Mean and sample std of the finite values (missing or NaN values are left out)."""
    xs = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    n = len(xs)
    if n == 0:
        return Spread(math.nan, math.nan, 0)
    mean = sum(xs) / n
    std = math.sqrt(sum((x - mean) ** 2 for x in xs) / (n - 1)) if n > 1 else math.nan
    return Spread(mean, std, n)


@dataclass(frozen=True)
class Difference:
    delta: float  # mean(row) - mean(reference)
    sigma: float  # the seed noise of delta: sqrt(std_row^2 / n_row + std_ref^2 / n_ref)


def difference(row: Spread, reference: Spread) -> Difference:
    """The row's mean minus the reference's, with the standard error of that difference of two means."""
    if row.n < 2 or reference.n < 2:
        return Difference(row.mean - reference.mean, math.nan)
    return Difference(row.mean - reference.mean, math.sqrt(row.std**2 / row.n + reference.std**2 / reference.n))


def verdict(ours: Difference, paper_delta: float | None) -> str | None:
    """Does our difference to the full model tell what the paper's does?

    - agrees: same sign as the paper's and |delta| > 2 sigma;
    - disagrees: opposite sign and |delta| > 2 sigma, or the paper saw no change (|paper delta| < 0.005) and ours is
      beyond 2 sigma;
    - within noise: |delta| <= 2 sigma (when the paper saw no change, that agrees with it: "agrees");
    - needs 2 seeds: the spread is unknown. None when the paper gives no number.
    """
    if paper_delta is None or math.isnan(ours.delta):
        return None
    if math.isnan(ours.sigma):
        return TOO_FEW
    significant = abs(ours.delta) > 2 * ours.sigma
    if abs(paper_delta) < 0.005:
        return DISAGREES if significant else AGREES
    if not significant:
        return WITHIN_NOISE
    return AGREES if (ours.delta > 0) == (paper_delta > 0) else DISAGREES


def against_reference(ours: Difference) -> str:
    """A row the paper has no number for (one of the project's forms, an extra variant) against the reference, on a
    metric where higher is better: better / worse beyond 2 sigma, otherwise within noise; needs 2 seeds when the
    spread is unknown."""
    if math.isnan(ours.sigma) or math.isnan(ours.delta):
        return TOO_FEW
    if abs(ours.delta) <= 2 * ours.sigma:
        return WITHIN_NOISE
    return BETTER if ours.delta > 0 else WORSE

"""Side-by-side runs of two variants: is the difference of their means more than the spread?

Live runs of the whole job differ from run to run (robots, edge and cloud race on two cores),
so an A/B benchmark runs each variant several times on the same data. :func:`mean_shift` says
how far apart the two sets of runs are and how likely a shift that large is by chance: a
one-sided permutation test (Fisher–Pitman) on the difference of the means, exact when the
relabellings are few, Monte Carlo with a fixed seed otherwise. No distribution is assumed,
which suits a handful of runs of a skewed quantity such as ATE.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np


class ComparisonError(ValueError):
    """The runs cannot be compared (too few, or not finite)."""


@dataclass(frozen=True)
class MeanShift:
    """``b`` against ``a``: means, ``change`` = mean(b) / mean(a) - 1, and ``p_greater``:
    the probability that randomly relabelled runs give a mean of ``b`` at least this much
    above ``a``'s (one-sided; small: ``b`` really is larger); ``exact`` whether every
    relabelling was counted."""

    mean_a: float
    mean_b: float
    change: float
    p_greater: float
    exact: bool


def mean_shift(a: list[float], b: list[float], rounds: int = 100_000, seed: int = 0) -> MeanShift:
    """Compare runs ``b`` with runs ``a`` (each ≥ 2 finite values, any unit)."""
    xa = np.asarray(a, np.float64).ravel()
    xb = np.asarray(b, np.float64).ravel()
    for name, x in (("a", xa), ("b", xb)):
        if x.size < 2:
            raise ComparisonError(f"runs {name}: need at least 2 values, got {x.size}")
        if not np.all(np.isfinite(x)):
            raise ComparisonError(f"runs {name}: values must be finite, got {x.tolist()}")
    pooled = np.concatenate([xa, xb])
    n, k = pooled.size, xb.size
    observed = xb.mean() - xa.mean()
    total = pooled.sum()
    tol = 1e-12 * max(1.0, float(np.abs(pooled).max()))

    def shifts(idx: np.ndarray) -> np.ndarray:
        """(R,) mean(b) - mean(a) when the rows of ``idx`` (R, k) are labelled b."""
        sb = pooled[idx].sum(axis=1)
        return sb / k - (total - sb) / (n - k)

    exact = math.comb(n, k) <= rounds
    if exact:
        idx = np.array(list(itertools.combinations(range(n), k)), np.int64)
    else:
        rng = np.random.default_rng(seed)
        idx = np.argsort(rng.random((rounds, n)), axis=1)[:, :k]
    hits = int(np.count_nonzero(shifts(idx) >= observed - tol))
    # Monte Carlo counts the observed labelling too (the estimate is then never 0).
    p = hits / idx.shape[0] if exact else (hits + 1) / (idx.shape[0] + 1)
    return MeanShift(
        mean_a=float(xa.mean()),
        mean_b=float(xb.mean()),
        change=float(observed / xa.mean()) if xa.mean() != 0 else math.inf,
        p_greater=float(p),
        exact=exact,
    )

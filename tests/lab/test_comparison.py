"""The A/B permutation test: exact p-values on small sets, Monte Carlo agreeing with them on
larger ones, and bad input refused."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lab.comparison import ComparisonError, mean_shift


def test_fully_separated_runs_get_the_smallest_exact_p() -> None:
    # 3 + 3 runs, b all above a: only the observed labelling is as extreme, 1 of C(6, 3).
    r = mean_shift([1.0, 2.0, 3.0], [4.0, 5.0, 6.0])
    assert r.exact
    assert r.p_greater == pytest.approx(1 / math.comb(6, 3))
    assert r.mean_a == pytest.approx(2.0) and r.mean_b == pytest.approx(5.0)
    assert r.change == pytest.approx(1.5)


def test_b_below_a_is_not_evidence_of_b_greater() -> None:
    r = mean_shift([4.0, 5.0, 6.0], [1.0, 2.0, 3.0])
    assert r.p_greater == pytest.approx(1.0)
    assert r.change < 0


def test_identical_distributions_give_a_large_p() -> None:
    rng = np.random.default_rng(3)
    a, b = rng.normal(1.0, 0.1, 8).tolist(), rng.normal(1.0, 0.1, 8).tolist()
    assert mean_shift(a, b).p_greater > 0.05


def test_monte_carlo_agrees_with_the_exact_count() -> None:
    a = [0.41, 0.31, 0.45, 0.52, 0.47, 0.48]
    b = [0.42, 0.40, 0.55, 0.59, 0.51, 0.57]
    exact = mean_shift(a, b)
    sampled = mean_shift(a, b, rounds=200, seed=1)  # C(12, 6) = 924 > 200: sampled
    assert exact.exact and not sampled.exact
    assert 0.0 < exact.p_greater < 0.5
    assert sampled.p_greater == pytest.approx(exact.p_greater, abs=0.06)


@pytest.mark.parametrize(
    ("a", "b", "match"),
    [
        ([1.0], [2.0, 3.0], "runs a: need at least 2"),
        ([1.0, 2.0], [float("nan"), 3.0], "runs b: values must be finite"),
    ],
)
def test_bad_runs_are_refused(a: list[float], b: list[float], match: str) -> None:
    with pytest.raises(ComparisonError, match=match):
        mean_shift(a, b)

"""The paired comparison of two recipes: standard error and Fisher's sign-flip test."""

from __future__ import annotations

import itertools
import math
import statistics

import numpy as np
import pytest

from dyngs.tools import paired
from dyngs.tools.paired import PairedChange, paired_change, sign_flip_p


def _brute_force_p(differences: list[float]) -> float:
    """The test's definition, written out: every sign assignment, one at a time."""
    observed = abs(sum(differences))
    far = 0
    for signs in itertools.product((1, -1), repeat=len(differences)):
        total = abs(sum(s * d for s, d in zip(signs, differences, strict=True)))
        far += total >= observed - 1e-12
    return far / 2 ** len(differences)


@pytest.mark.parametrize("seed", range(5))
def test_exact_p_is_the_brute_force_enumeration(seed: int) -> None:
    rng = np.random.default_rng(seed)
    differences = list(rng.normal(0.3 * seed, 1.0, size=int(rng.integers(2, 11))))
    assert sign_flip_p(differences) == pytest.approx(_brute_force_p(differences), abs=1e-12)


def test_p_at_the_extremes() -> None:
    assert sign_flip_p([1.0] * 5) == 2 / 2**5  # all up: only all-up and all-down are as far
    assert sign_flip_p([1.0, -1.0, 2.0, -2.0]) == 1.0  # a mean of zero is as far as any
    assert sign_flip_p([0.7]) == 1.0  # one pair says nothing
    assert sign_flip_p(list(range(1, 21))) == 2 / 2**20  # the largest exact case


def test_random_draws_agree_with_the_exact_p(monkeypatch: pytest.MonkeyPatch) -> None:
    """Beyond EXACT_PAIRS the p-value is estimated; on a case still cheap to enumerate
    the estimate lies within a few of its standard errors of the exact value."""
    rng = np.random.default_rng(7)
    differences = list(rng.normal(0.25, 1.0, size=paired.EXACT_PAIRS + 1))
    estimated = sign_flip_p(differences, draws=100_000)
    monkeypatch.setattr(paired, "EXACT_PAIRS", len(differences))
    exact = sign_flip_p(differences)
    assert 0.01 < exact < 0.99  # a case where the estimate has something to get right
    assert estimated == pytest.approx(exact, abs=5 * math.sqrt(0.25 / 100_000))
    monkeypatch.undo()
    assert sign_flip_p(differences, draws=100_000) == estimated  # seeded: the same every run


def test_paired_change_statistics() -> None:
    base = [27.54, 28.02, 28.17, 38.19, 37.85]
    variant = [28.25, 27.26, 28.77, 38.53, 38.03]
    change = paired_change(base, variant)
    differences = [v - b for b, v in zip(base, variant, strict=True)]
    assert change.n == 5 and change.wins == 4
    assert change.mean == pytest.approx(statistics.fmean(differences))
    assert change.std == pytest.approx(statistics.stdev(differences))
    assert change.stderr == pytest.approx(statistics.stdev(differences) / math.sqrt(5))
    assert change.p == pytest.approx(_brute_force_p(differences))
    assert change.verdict() == "within noise"
    assert "4 of 5 up" in change.describe()
    single = paired_change([30.0], [31.0])
    assert (single.std, single.stderr, single.p) == (None, None, 1.0)


def test_verdict_needs_p_below_the_level() -> None:
    def change(mean: float, p: float) -> PairedChange:
        return PairedChange(n=8, mean=mean, std=1.0, stderr=0.35, p=p, wins=6)

    assert change(0.5, 0.01).verdict() == "gain"
    assert change(-0.5, 0.01).verdict() == "loss"
    assert change(0.5, 0.05).verdict() == "within noise"
    assert change(0.5, 0.08).verdict(level=0.1) == "gain"


@pytest.mark.parametrize(
    ("differences", "message"),
    [([], "no differences"), ([0.1, math.nan], "finite"), ([0.1, math.inf], "finite")],
)
def test_bad_differences_are_refused(differences: list[float], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        sign_flip_p(differences)


def test_unequal_lengths_are_refused() -> None:
    with pytest.raises(ValueError, match="2 base values against 3 variant values"):
        paired_change([1.0, 2.0], [1.0, 2.0, 3.0])

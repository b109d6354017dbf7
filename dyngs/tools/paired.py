"""Is a change a gain? Paired differences over seeds, their standard error, and an exact
sign-flip test.

A training run's PSNR moves by a fraction of a dB to a few dB with its seed (its initial
cloud, its view order) and with the rounding of anything upstream, so one run of each of
two recipes says little. Running both on the same seeds and scenes, and looking at the
differences pair by pair, removes what a seed does to both alike. What is left is each
pair's own noise, and the question is whether the mean difference stands out of it.

The test here is Fisher's randomisation test for paired data (Fisher 1935, *The Design of
Experiments*, on Darwin's paired Zea mays plants): if the change did nothing, each
pair's difference would be as likely to have come out with the other sign, so the
p-value is the share of the 2ⁿ sign assignments whose mean is at least as far from zero
as the one observed. It assumes no
distribution (our differences are not normal: a seed that collapses gives one pair of
−9 dB among pairs of ±0.5), it is exact for n ≤ `EXACT_PAIRS`, and beyond that it is
estimated from `DRAWS` seeded random assignments.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

EXACT_PAIRS = 20
"""Up to this many pairs every sign assignment is enumerated (2²⁰ ≈ 10⁶ sums)."""

DRAWS = 200_000
"""Random sign assignments beyond `EXACT_PAIRS` (p then carries a standard error of at
most √(0.25 / DRAWS) ≈ 0.001)."""


@dataclass(frozen=True)
class PairedChange:
    """The paired differences of a variant against a base (variant − base)."""

    n: int
    mean: float
    std: float | None
    """Sample standard deviation of the differences (None for one pair)."""
    stderr: float | None
    """Standard error of the mean difference, std / √n (None for one pair)."""
    p: float
    """Two-sided p-value of the sign-flip test: the chance of a mean at least this far
    from zero if the change did nothing. 1 for a single pair."""
    wins: int
    """Pairs in which the variant came out higher."""

    def verdict(self, level: float = 0.05) -> str:
        """A gain or a loss when p < `level` (by the sign of the mean), else "within noise"."""
        if self.p >= level:
            return "within noise"
        return "gain" if self.mean > 0 else "loss"

    def describe(self, digits: int = 2) -> str:
        """One line, e.g. `+0.31 ± 0.19 dB (SE; 12 of 19 up, p = 0.13: within noise)`."""
        spread = "" if self.stderr is None else f" ± {self.stderr:.{digits}f}"
        return (f"{self.mean:+.{digits}f}{spread} (SE; {self.wins} of {self.n} up, "
                f"p = {self.p:.3g}: {self.verdict()})")  # fmt: skip


def sign_flip_p(differences: Sequence[float], draws: int = DRAWS, seed: int = 0) -> float:
    """Two-sided p-value of Fisher's sign-flip test for paired differences: the share of
    sign assignments (every one for up to `EXACT_PAIRS`, else `draws` seeded random ones)
    whose |Σ| is at least the observed |Σ|. The observed assignment counts, so p > 0."""
    d = np.abs(np.asarray(differences, dtype=np.float64))
    if d.ndim != 1 or not np.isfinite(d).all():
        raise ValueError(f"differences must be a list of finite numbers, got {differences!r}")
    if d.size == 0:
        raise ValueError("no differences to test")
    observed = abs(float(np.sum(differences)))
    # A sum equal to the observed one up to rounding counts as at least as far.
    tolerance = 1e-9 * max(float(d.sum()), 1.0)
    if d.size <= EXACT_PAIRS:
        return float(np.mean(np.abs(_every_signed_sum(d)) >= observed - tolerance))
    rng = np.random.default_rng(seed)
    far = 0
    for start in range(0, draws, 50_000):
        batch = min(50_000, draws - start)
        signs = rng.integers(0, 2, size=(batch, d.size)) * 2.0 - 1.0
        far += int(np.sum(np.abs(signs @ d) >= observed - tolerance))
    return (far + 1) / (draws + 1)  # the observed assignment is one of them


def _every_signed_sum(values: np.ndarray) -> np.ndarray:
    """±v₁ ± v₂ … ± vₙ for all 2ⁿ choices of signs, built one value at a time (2ⁿ floats
    of memory, 8 MB at `EXACT_PAIRS`)."""
    sums = np.zeros(1)
    for value in values:
        sums = np.concatenate([sums + value, sums - value])
    return sums


def paired_change(base: Sequence[float], variant: Sequence[float]) -> PairedChange:
    """Compare `variant` with `base`, entry i of one paired with entry i of the other (the
    same scene and seed)."""
    if len(base) != len(variant):
        raise ValueError(f"{len(base)} base values against {len(variant)} variant values")
    differences = [v - b for b, v in zip(base, variant, strict=True)]
    n = len(differences)
    std = statistics.stdev(differences) if n > 1 else None
    return PairedChange(
        n=n,
        mean=statistics.fmean(differences),
        std=std,
        stderr=None if std is None else std / math.sqrt(n),
        p=sign_flip_p(differences),
        wins=sum(d > 0 for d in differences),
    )

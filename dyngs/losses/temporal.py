"""Priors on the time planes of a plane-based field (K-Planes, Fridovich-Keil et al. 2023).

Letters: F feature channels, T cells along time, R along the spatial axis. Time planes
are [F, T, R] with time along dim −2 (dyngs.fields.base.PlaneGrids); any leading
dimensions are allowed.

Scale. K-Planes and 4DGaussians (Wu et al. 2024) *sum* these terms over planes and
resolutions; here they are *means* over planes, so a weight taken from those papers
matches ours multiplied by the number of time planes.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor


def _whole_mean(terms: Tensor, count: int | None) -> Tensor:
    """The mean of `terms`, or their sum ÷ `count` (the terms a whole plane would have)."""
    return terms.mean() if count is None else terms.sum() / count


def _counts(
    planes: list[Tensor], whole: list[tuple[int, int]] | None, lost: int
) -> list[int | None]:
    """Per plane, F·(T − lost)·R of its whole [T, R] size, or None (its own mean)."""
    if not whole:
        return [None] * len(planes)
    return [p[..., 0, 0].numel() * (t - lost) * r for p, (t, r) in zip(planes, whole, strict=True)]


def time_smoothness(
    time_planes: list[Float[Tensor, "*F T R"]], whole: list[tuple[int, int]] | None = None
) -> Float[Tensor, ""]:
    """K-Planes' temporal smoothness: mean squared second difference along time (dim −2),
    averaged over planes. A plane linear in t costs 0; 0 for an empty list.

    `whole`, per plane, the [T, R] it had before the field was cut to what queries it
    (`dyngs.fields.base.PlaneGrids.temporal_whole`): each plane's terms are then divided by
    the whole plane's count, so a kept cell's share and gradient stay what they were."""
    if not time_planes:
        return torch.zeros(())
    per_plane = []
    for p, count in zip(time_planes, _counts(time_planes, whole, 2), strict=True):
        if p.shape[-2] < 3:  # fewer than three time cells: no second difference, no cost
            per_plane.append(p.new_zeros(()))
        else:
            per_plane.append(_whole_mean(p.diff(n=2, dim=-2).square(), count))
    return torch.stack(per_plane).mean()


def time_l1_to_static(
    time_planes: list[Float[Tensor, "*F T R"]], whole: list[tuple[int, int]] | None = None
) -> Float[Tensor, ""]:
    """K-Planes' sparse-transients prior: mean |1 − plane|, averaged over planes (`whole`
    as in `time_smoothness`).

    Time planes multiply the spatial features (K-Planes' Hadamard product), so a plane
    of ones leaves them untouched: the pull toward 1 is a pull toward a static scene.
    """
    if not time_planes:
        return torch.zeros(())
    counts = _counts(time_planes, whole, 0)
    per_plane = [
        _whole_mean((1.0 - p).abs(), count) for p, count in zip(time_planes, counts, strict=True)
    ]
    return torch.stack(per_plane).mean()

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


def _mean_square_second_difference(plane: Tensor) -> Tensor:
    if plane.shape[-2] < 3:  # fewer than three time cells: no second difference, no cost
        return plane.new_zeros(())
    return plane.diff(n=2, dim=-2).square().mean()


def time_smoothness(time_planes: list[Float[Tensor, "*F T R"]]) -> Float[Tensor, ""]:
    """K-Planes' temporal smoothness: mean squared second difference along time (dim −2),
    averaged over planes. A plane linear in t costs 0; 0 for an empty list."""
    if not time_planes:
        return torch.zeros(())
    return torch.stack([_mean_square_second_difference(p) for p in time_planes]).mean()


def time_l1_to_static(time_planes: list[Float[Tensor, "*F T R"]]) -> Float[Tensor, ""]:
    """K-Planes' sparse-transients prior: mean |1 − plane|, averaged over planes.

    Time planes multiply the spatial features (K-Planes' Hadamard product), so a plane
    of ones leaves them untouched: the pull toward 1 is a pull toward a static scene.
    """
    if not time_planes:
        return torch.zeros(())
    return torch.stack([(1.0 - p).abs().mean() for p in time_planes]).mean()

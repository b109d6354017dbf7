"""Total variation of the spatial feature planes (K-Planes, Fridovich-Keil et al. 2023).

Letters: F feature channels, R1×R0 cells of a spatial plane ([F, R1, R0], any leading
dimensions allowed: only the last two are plane axes).

Scale. K-Planes' `compute_plane_tv` is 2·(mean_h + mean_w) and K-Planes and 4DGaussians
(Wu et al. 2024) *sum* it over planes and resolutions. Here a plane's TV is
mean_h + mean_w and the result is the *mean* over planes, so a weight taken from those
papers matches ours multiplied by 2 × (number of spatial planes).
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor


def _mean_square_step(plane: Tensor, dim: int) -> Tensor:
    """Mean squared difference of neighbouring cells along `dim` (0 if it has one cell)."""
    if plane.shape[dim] < 2:
        return plane.new_zeros(())
    return plane.diff(dim=dim).square().mean()


def plane_tv(planes: list[Float[Tensor, "*F R1 R0"]]) -> Float[Tensor, ""]:
    """Mean over planes of the mean squared neighbour difference along each plane axis,
    summed over the two axes; a zero tensor for an empty list (fields without planes)."""
    if not planes:
        return torch.zeros(())
    per_plane = [_mean_square_step(p, -2) + _mean_square_step(p, -1) for p in planes]
    return torch.stack(per_plane).mean()

"""Smoothness priors on the spatial feature planes: K-Planes' total variation
(Fridovich-Keil et al. 2023) and its scale-free form, the planes' roughness.

Letters: F feature channels, R1×R0 cells of a spatial plane ([F, R1, R0], any leading
dimensions allowed: only the last two are plane axes).

Why a scale-free form. The TV is smallest for a plane that does not vary at all, so
besides smoothing a field it also shrinks it, and under Adam (which takes steps of the
learning rate's size whichever term dominates a cell's gradient) a strong TV can flatten
the deformation field before the photometric loss has taught it any motion: at 30× the
default weight one thin_structure seed ended with every spatial plane flat to within 1e-7
and its motion carried by temporal Gaussians alone (docs/ACCURACY.md). `plane_roughness`
divides each channel's squared neighbour differences by that channel's variance over the
plane: a Rayleigh quotient of the grid's Laplacian, which a field lowers by varying more
smoothly, not by varying less. Scaling a channel leaves it unchanged.

Scale. K-Planes' `compute_plane_tv` is 2·(mean_h + mean_w) and K-Planes and 4DGaussians
(Wu et al. 2024) *sum* it over planes and resolutions. Here a plane's TV is
mean_h + mean_w and the result is the *mean* over planes, so a weight taken from those
papers matches ours multiplied by 2 × (number of spatial planes).
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor


def _mean_square_step(plane: Tensor, dim: int, whole: tuple[int, int] | None = None) -> Tensor:
    """Mean squared difference of neighbouring cells along `dim`, −2 or −1 (0 if it has
    one cell); with `whole`, their sum divided by the count of steps along `dim` in a
    plane of that [R1, R0] size (see `plane_tv`)."""
    if plane.shape[dim] < 2:
        return plane.new_zeros(())
    squares = plane.diff(dim=dim).square()
    if whole is None:
        return squares.mean()
    rows, columns = whole
    steps = (rows - 1) * columns if dim == -2 else rows * (columns - 1)
    return squares.sum() / (plane[..., 0, 0].numel() * steps)


def plane_tv(
    planes: list[Float[Tensor, "*F R1 R0"]], whole: list[tuple[int, int]] | None = None
) -> Float[Tensor, ""]:
    """Mean over planes of the mean squared neighbour difference along each plane axis,
    summed over the two axes; a zero tensor for an empty list (fields without planes).

    `whole`, per plane, the [R1, R0] it had before the field was cut to what queries it
    (`dyngs.fields.base.PlaneGrids.spatial_whole`): each plane's squared steps are then
    divided by the whole plane's count, so a kept cell's share of the term, and its
    gradient, are what they were before the cut."""
    if not planes:
        return torch.zeros(())
    sizes: list[tuple[int, int] | None] = list(whole) if whole else [None] * len(planes)
    per_plane = [
        _mean_square_step(p, -2, size) + _mean_square_step(p, -1, size)
        for p, size in zip(planes, sizes, strict=True)
    ]
    return torch.stack(per_plane).mean()


def _channel_steps(plane: Tensor, dim: int) -> Tensor:
    """Per channel (all leading dimensions kept), the mean squared difference of
    neighbouring cells along `dim` (0 if it has one cell)."""
    if plane.shape[dim] < 2:
        return plane.new_zeros(plane.shape[:-2])
    return plane.diff(dim=dim).square().mean((-2, -1))


def plane_roughness(
    planes: list[Float[Tensor, "*F R1 R0"]], eps: float = 1e-6
) -> Float[Tensor, ""]:
    """Mean over planes and channels of (squared neighbour differences along both axes, as
    `plane_tv`) ÷ (the channel's sample variance over the plane's cells + `eps`); a zero
    tensor for an empty list. About 4 for independent noise, about (2π/R)² for a sine of one
    period along R cells, and the same for a channel scaled by any factor: a measure of
    how rough the features are, not how large. `eps` keeps a constant channel finite."""
    if not planes:
        return torch.zeros(())
    per_plane = []
    for p in planes:
        steps = _channel_steps(p, -2) + _channel_steps(p, -1)
        spread = p.flatten(-2).var(-1) if p.shape[-2] * p.shape[-1] > 1 else p.new_zeros(())
        per_plane.append((steps / (spread + eps)).mean())
    return torch.stack(per_plane).mean()

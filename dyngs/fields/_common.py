"""Helpers shared by the fields and the head.

Letters: N points.
"""

from __future__ import annotations

import math

import torch
from jaxtyping import Float
from torch import Tensor, nn

from dyngs.ops import zero_nonfinite
from dyngs.types import SceneBox


def space_time(
    box: SceneBox, xyz: Float[Tensor, "N 3"], t: Float[Tensor, "N 1"]
) -> Float[Tensor, "N 4"]:
    """(x, y, z, t) in field units: space normalised by `box` to [-1, 1]³ and t ∈ [0, 1]
    mapped to 2t − 1 (docs/DESIGN.md). Not clamped. `t` may also be [1, 1], one time for all.

    A non-finite coordinate (a NaN or ±Inf mean, which the renderers cull and count) is
    replaced by 0, the box centre or mid-time, with zero gradient: a NaN reaching
    `grid_sample`'s backward crashed the process (an out-of-bounds write), and in the MLP it
    made NaN hidden activations, whose weight gradients NaN × 0 = NaN spoilt every row.

    The box corners are built from Python floats in the input's dtype, so float64 inputs
    are normalised to float64 precision."""
    n = xyz.shape[0]
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must be [N, 3], got {tuple(xyz.shape)}")
    if t.ndim != 2 or t.shape[1] != 1 or t.shape[0] not in (n, 1):
        raise ValueError(f"t must be [N, 1] (or [1, 1]) for N = {n}, got {tuple(t.shape)}")
    coords = torch.cat([box.normalize(xyz), (t * 2.0 - 1.0).expand(n, 1)], dim=1)
    return zero_nonfinite(coords)


def init_linear_(layer: nn.Linear, generator: torch.Generator | None = None) -> nn.Linear:
    """PyTorch's default Linear initialisation, U(±1/√fan_in) for weight and bias, drawn
    from `generator` so that a run's weights follow its own seed rather than the global one."""
    bound = 1.0 / math.sqrt(layer.in_features) if layer.in_features > 0 else 0.0
    with torch.no_grad():
        layer.weight.uniform_(-bound, bound, generator=generator)
        if layer.bias is not None:
            layer.bias.uniform_(-bound, bound, generator=generator)
    return layer

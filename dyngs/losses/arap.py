"""Local rigidity: neighbour distances kept between two times (as-rigid-as-possible).

Letters: N points (Gaussian centres), K neighbours per point, C rows in a chunk.

The term is the isometry prior of Dynamic 3D Gaussians (Luiten et al. 2024), also used
by SC-GS (Huang et al. 2024): pick each Gaussian's K nearest neighbours in the canonical
(or first) frame, weight them by a Gaussian falloff of their canonical distance, and
penalise any change of the distance ‖x_i − x_j‖ between two times. A rigid motion of
the whole set costs exactly 0; stretching or tearing a neighbourhood costs its change in
length.
"""

from __future__ import annotations

import torch
from jaxtyping import Float, Int
from torch import Tensor

from dyngs.ops import gather

SAFE_NORM_EPS = 1e-12
"""ε in √(d² + ε), in squared length units: a 1e-6 floor on a length (see `safe_norm`)."""


def safe_norm(v: Float[Tensor, "*B 3"], eps: float = SAFE_NORM_EPS) -> Float[Tensor, "*B"]:
    """√(‖v‖² + ε): the Euclidean length with a finite gradient at v = 0.

    d‖v‖/dv = v/‖v‖ is 0/0 at v = 0 (coincident neighbours: clones right after a
    densification split, duplicated input points), and autograd would return NaN through
    `sqrt`. With ε the gradient is v/√(‖v‖² + ε): 0 at v = 0 and of length < 1 everywhere.
    The value is off by at most √ε = 1e-6 at 0 and by ε/(2‖v‖) elsewhere, and since both
    times get the same offset it nearly cancels in a difference of two lengths.
    """
    return (v.square().sum(dim=-1) + eps).sqrt()


def neighbor_weights(
    points: Float[Tensor, "N 3"], neighbors: Int[Tensor, "N K"], scale: float
) -> Float[Tensor, "N K"]:
    """exp(−‖x_i − x_j‖² / scale²): a Gaussian falloff on canonical distances.

    Dynamic 3D Gaussians writes exp(−λ_w d²) with λ_w = 2000, i.e. scale = 1/√2000 ≈ 0.022
    scene units; a scale tied to the mean neighbour distance adapts to the point density.
    """
    if neighbors.numel() > 0 and not scale > 0.0:  # NaN fails too
        raise ValueError(f"scale must be positive, got {scale}")
    d2 = (points[:, None, :] - points[neighbors]).square().sum(dim=-1)
    return torch.exp(-d2 / (scale * scale))


def arap_loss(
    pos_a: Float[Tensor, "N 3"],
    pos_b: Float[Tensor, "N 3"],
    neighbors: Int[Tensor, "N K"],
    weights: Float[Tensor, "N K"],
) -> Float[Tensor, ""]:
    """Weighted mean over pairs (i, j) of |‖x_i(a) − x_j(a)‖ − ‖x_i(b) − x_j(b)‖|.

    Σ w·|Δd| / Σ w, so the value is a length (scene units) whatever the falloff; Dynamic
    3D Gaussians takes mean(w·|Δd|) instead, which is ours times mean(w). 0 when there
    are no pairs or every weight is 0. Lengths use `safe_norm`, so coincident neighbours
    give a finite value and gradient.
    """
    if pos_a.shape != pos_b.shape or neighbors.shape != weights.shape:
        raise ValueError(
            f"shape mismatch: pos {tuple(pos_a.shape)} vs {tuple(pos_b.shape)}, "
            f"neighbors {tuple(neighbors.shape)} vs weights {tuple(weights.shape)}"
        )
    length_a = safe_norm(pos_a[:, None, :] - gather(pos_a, neighbors))
    length_b = safe_norm(pos_b[:, None, :] - gather(pos_b, neighbors))
    weighted = (weights * (length_a - length_b).abs()).sum()
    # The denominator is 0 only when every weight is, and then so is the numerator.
    return weighted / weights.sum().clamp_min(torch.finfo(weights.dtype).tiny)

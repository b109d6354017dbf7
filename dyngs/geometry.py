"""Quaternion and covariance helpers shared by the model and the renderers.

Quaternions are (w, x, y, z). Letters: N items.
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor


def normalize_quaternion(q: Float[Tensor, "N 4"], eps: float = 1e-12) -> Float[Tensor, "N 4"]:
    """Unit quaternions that stay finite for any finite input.

    The input is first divided by its largest |component| (detached: normalisation is
    scale-invariant, so the gradient is unchanged) so that norms of 1e-20 or 1e20 neither
    underflow nor overflow when squared. A zero quaternion stays zero, which
    `quaternion_to_rotation` turns into the identity rather than NaN.
    """
    scale = q.detach().abs().amax(dim=-1, keepdim=True)
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    q = q / scale
    return q / q.norm(dim=-1, keepdim=True).clamp_min(eps)


def quaternion_to_rotation(q: Float[Tensor, "N 4"]) -> Float[Tensor, "N 3 3"]:
    """Rotation matrices of unit quaternions (a zero quaternion gives the identity)."""
    w, x, y, z = q.unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def quaternion_multiply(a: Float[Tensor, "N 4"], b: Float[Tensor, "N 4"]) -> Float[Tensor, "N 4"]:
    """Hamilton product a ⊗ b (apply b first, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def covariance_3d(
    quats: Float[Tensor, "N 4"], scales: Float[Tensor, "N 3"], eps: float = 1e-12
) -> Float[Tensor, "N 3 3"]:
    """Σ = R S Sᵀ Rᵀ from (not necessarily unit) quaternions and standard deviations."""
    m = quaternion_to_rotation(normalize_quaternion(quats, eps)) * scales[..., None, :]
    return m @ m.transpose(-1, -2)

"""Real spherical harmonics up to degree 3, in the basis and sign convention of
Plenoxels / 3D Gaussian Splatting (Kerbl et al. 2023), so coefficients exported by dyngs
read correctly in common 3DGS viewers.

Letters: N items, K coefficients per channel ((degree + 1)² are used).
"""

from __future__ import annotations

import math

import torch
from jaxtyping import Float
from torch import Tensor

# Normalisation constants of the real spherical harmonics Y_lm, sqrt((2l+1)/(4π)·(l-m)!/(l+m)!)
# times the polynomial factors; degree-1 signs follow the Condon–Shortley phase.
SH_C0 = 0.5 / math.sqrt(math.pi)
SH_C1 = math.sqrt(3.0 / (4.0 * math.pi))
SH_C2 = (
    0.5 * math.sqrt(15.0 / math.pi),
    -0.5 * math.sqrt(15.0 / math.pi),
    0.25 * math.sqrt(5.0 / math.pi),
    -0.5 * math.sqrt(15.0 / math.pi),
    0.25 * math.sqrt(15.0 / math.pi),
)
SH_C3 = (
    -0.25 * math.sqrt(35.0 / (2.0 * math.pi)),
    0.5 * math.sqrt(105.0 / math.pi),
    -0.25 * math.sqrt(21.0 / (2.0 * math.pi)),
    0.25 * math.sqrt(7.0 / math.pi),
    -0.25 * math.sqrt(21.0 / (2.0 * math.pi)),
    0.25 * math.sqrt(105.0 / math.pi),
    -0.25 * math.sqrt(35.0 / (2.0 * math.pi)),
)


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Float[Tensor, "N 3"]) -> Float[Tensor, "N K"]:
    """The (degree + 1)² basis functions at unit directions."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(
    degree: int, coeffs: Float[Tensor, "N K 3"], dirs: Float[Tensor, "N 3"]
) -> Float[Tensor, "N 3"]:
    """RGB seen along `dirs`: Σ_k c_k Y_k(dir) + 0.5, clamped below at 0 as in 3DGS.

    `dirs` need not be unit length; a zero direction keeps only the degree-0 term instead
    of producing NaN.
    """
    if degree == 0:
        return eval_sh0(coeffs)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(degree, dirs)
    rgb = (basis[..., None] * coeffs[..., : basis.shape[-1], :]).sum(dim=-2)
    return (rgb + 0.5).clamp_min(0.0)


def eval_sh0(coeffs: Float[Tensor, "N K 3"]) -> Float[Tensor, "N 3"]:
    """`eval_sh` at degree 0, which needs no direction: Y₀ is the constant SH_C0, so the
    colour is c₀·SH_C0 + 0.5 (clamped at 0) whichever way the Gaussian is seen. The same
    values and gradients, to the bit, as the general formula at degree 0 (a sum over one
    coefficient), without normalising a direction that nothing reads; a renderer calls
    this before it forms the directions, and skips them too. Most scenes train at degree
    0 until the view-dependent error asks for more (`--gaussians.sh-evidence`): on the
    demo, the whole run."""
    return (coeffs[..., 0, :] * SH_C0 + 0.5).clamp_min(0.0)


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """The degree-0 coefficient that evaluates to `rgb` in every direction."""
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(sh0: Tensor) -> Tensor:
    return sh0 * SH_C0 + 0.5

"""The compiled view-dependent colours of `cpu-tile` (numba): `sh.eval_sh` from the
camera-relative means, forward and backward, in one pass over the Gaussians each.

`sh.eval_sh` is the specification: the real spherical harmonics of 3D Gaussian Splatting
(Kerbl et al. 2023) up to degree 3, at the unit direction from the camera centre to the
mean, plus 0.5, clamped below at 0. In PyTorch that is some forty whole-array operations
at degree 1 and a hundred at degree 3, forward and backward, each a pass over memory and
a dispatch: about 3 ms a training step on the demo's ~7 000 Gaussians at degree 1, which
every step draws (the band above the active one is drawn at zero to gather evidence for
it). Here each direction is one pass. Every Gaussian's arithmetic is in float64 and the
results are rounded once to the inputs' dtype, so they agree with the specification to
its own float32 rounding, not to the bit. The backward is the chain rule written out:
the clamp passes the gradient where its input is ≥ 0, the normalisation where the norm
is ≥ its floor (1e-12; below it, the direction is divided by the floor), as PyTorch's
clamp_min passes them. tests/renderers/test_sh_kernels.py holds both directions to
`eval_sh` and gradcheck in float64.

Letters: N Gaussians, K = (degree + 1)² coefficients a channel.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from dyngs.sh import SH_C0, SH_C1, SH_C2, SH_C3

NORM_FLOOR = 1e-12
"""`eval_sh`'s floor on a direction's norm (a zero direction keeps only degree 0)."""

CHUNK = 256
"""Gaussians a job takes; each Gaussian's results are its own, so the split changes no
digit."""


@njit(cache=True, nogil=True, inline="always")
def _basis(x, y, z, degree, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    """The (degree + 1)² basis functions at the unit direction (x, y, z), as `sh_basis`."""
    out[0] = SH_C0
    if degree >= 1:
        out[1], out[2], out[3] = -SH_C1 * y, SH_C1 * z, -SH_C1 * x
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out[4] = SH_C2[0] * x * y
        out[5] = SH_C2[1] * y * z
        out[6] = SH_C2[2] * (2 * zz - xx - yy)
        out[7] = SH_C2[3] * x * z
        out[8] = SH_C2[4] * (xx - yy)
        if degree >= 3:
            out[9] = SH_C3[0] * y * (3 * xx - yy)
            out[10] = SH_C3[1] * x * y * z
            out[11] = SH_C3[2] * y * (4 * zz - xx - yy)
            out[12] = SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy)
            out[13] = SH_C3[4] * x * (4 * zz - xx - yy)
            out[14] = SH_C3[5] * z * (xx - yy)
            out[15] = SH_C3[6] * x * (xx - 3 * yy)


@njit(cache=True, nogil=True, inline="always")
def _basis_pull(x, y, z, degree, pull):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Σ_k pull[k] · ∇Y_k at the unit direction (x, y, z): the gradient on the direction
    of a loss whose gradient on each basis function is pull[k]."""
    gx = gy = gz = 0.0
    if degree >= 1:
        gx -= SH_C1 * pull[3]
        gy -= SH_C1 * pull[1]
        gz += SH_C1 * pull[2]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        a, b, c, d, e = pull[4] * SH_C2[0], pull[5] * SH_C2[1], pull[6] * SH_C2[2], \
            pull[7] * SH_C2[3], pull[8] * SH_C2[4]  # fmt: skip
        gx += a * y - 2 * c * x + d * z + 2 * e * x
        gy += a * x + b * z - 2 * c * y - 2 * e * y
        gz += b * y + 4 * c * z + d * x
        if degree >= 3:
            p0, p1, p2 = pull[9] * SH_C3[0], pull[10] * SH_C3[1], pull[11] * SH_C3[2]
            p3, p4, p5 = pull[12] * SH_C3[3], pull[13] * SH_C3[4], pull[14] * SH_C3[5]
            p6 = pull[15] * SH_C3[6]
            gx += (p0 * 6 * x * y + p1 * y * z - p2 * 2 * x * y - p3 * 6 * x * z
                   + p4 * (4 * zz - 3 * xx - yy) + p5 * 2 * x * z + p6 * 3 * (xx - yy))  # fmt: skip
            gy += (p0 * 3 * (xx - yy) + p1 * x * z + p2 * (4 * zz - xx - 3 * yy)
                   - p3 * 6 * y * z - p4 * 2 * x * y - p5 * 2 * y * z - p6 * 6 * x * y)  # fmt: skip
            gz += (p1 * x * y + p2 * 8 * y * z + p3 * (6 * zz - 3 * xx - 3 * yy)
                   + p4 * 8 * x * z + p5 * (xx - yy))  # fmt: skip
    return gx, gy, gz


@njit(cache=True, nogil=True, inline="always")
def _direction(means, center, n):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Gaussian n's camera-relative mean d in float64, its norm and the divisor
    max(norm, floor), and the unit direction d / divisor."""
    dx = np.float64(means[n, 0]) - center[0]
    dy = np.float64(means[n, 1]) - center[1]
    dz = np.float64(means[n, 2]) - center[2]
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    divisor = max(norm, NORM_FLOOR)
    return dx, dy, dz, norm, divisor, dx / divisor, dy / divisor, dz / divisor


@njit(cache=True, nogil=True, inline="always")
def _unclamped(basis, coeffs, n, c):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Channel c of Gaussian n before the clamp, Σ_k Y_k · coeffs[n, k, c] + 0.5, in float64:
    the forward's value, and the backward's test of where the clamp passes the gradient."""
    total = 0.0
    for k in range(coeffs.shape[1]):
        total += basis[k] * np.float64(coeffs[n, k, c])
    return total + 0.5


@njit(parallel=True, cache=True, nogil=True, error_model="numpy")
def sh_forward(coeffs, means, center, degree, rgb):  # type: ignore[no-untyped-def]  # pragma: no cover
    """rgb[n] = max(Σ_k Y_k(dir_n) · coeffs[n, k] + 0.5, 0), dir_n = means[n] − center;
    coeffs [N, K, 3], means [N, 3], center [3] (float64), rgb [N, 3]."""
    n_all = rgb.shape[0]
    for job in prange((n_all + CHUNK - 1) // CHUNK):
        basis = np.empty(16)
        for n in range(job * CHUNK, min(job * CHUNK + CHUNK, n_all)):
            _, _, _, _, _, x, y, z = _direction(means, center, n)
            _basis(x, y, z, degree, basis)
            for c in range(3):
                rgb[n, c] = max(_unclamped(basis, coeffs, n, c), 0.0)


@njit(parallel=True, cache=True, nogil=True, error_model="numpy")
def sh_backward(coeffs, means, center, degree, upstream, coeffs_grad, means_grad):  # type: ignore[no-untyped-def]  # pragma: no cover
    """From upstream [N, 3], the gradient of `sh_forward`'s rgb: coeffs_grad [N, K, 3] and
    means_grad [N, 3] (empty when the means want none)."""
    n_all = upstream.shape[0]
    with_means = means_grad.shape[0] > 0
    for job in prange((n_all + CHUNK - 1) // CHUNK):
        basis, pull = np.empty(16), np.empty(16)
        passed = np.empty(3)
        for n in range(job * CHUNK, min(job * CHUNK + CHUNK, n_all)):
            dx, dy, dz, norm, divisor, x, y, z = _direction(means, center, n)
            _basis(x, y, z, degree, basis)
            for c in range(3):  # the clamp's gradient: where its input is ≥ 0
                free = _unclamped(basis, coeffs, n, c) >= 0.0
                passed[c] = np.float64(upstream[n, c]) if free else 0.0
            for k in range(coeffs.shape[1]):
                pull[k] = 0.0
                for c in range(3):
                    coeffs_grad[n, k, c] = basis[k] * passed[c]
                    pull[k] += passed[c] * np.float64(coeffs[n, k, c])
            if not with_means:
                continue
            ux, uy, uz = _basis_pull(x, y, z, degree, pull)
            # d / divisor: its gradient on d, and through the divisor (the norm, where it
            # is at least the floor) its projection along d.
            gx, gy, gz = ux / divisor, uy / divisor, uz / divisor
            if norm >= NORM_FLOOR:
                along = (ux * dx + uy * dy + uz * dz) / (divisor * divisor * norm)
                gx, gy, gz = gx - along * dx, gy - along * dy, gz - along * dz
            means_grad[n, 0], means_grad[n, 1], means_grad[n, 2] = gx, gy, gz

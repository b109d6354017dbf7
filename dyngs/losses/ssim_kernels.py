"""SSIM from its blurred moments as compiled kernels (numba): the map, and its gradient
with respect to the prediction's moments, one pass each over the pixels.

Letters: x the prediction, y the target; μx, μy, ⟨x²⟩, ⟨y²⟩, ⟨xy⟩ their blurred moments
(SSIM's Gaussian window, `blur_kernels`), flattened over channels and pixels.

The map is Wang et al. 2004's, with c1 = (0.01)², c2 = (0.03)² for data range 1:

    SSIM = a1·a2 / (b1·b2),  a1 = 2 μx μy + c1,  a2 = 2 (⟨xy⟩ − μx μy) + c2,
                             b1 = μx² + μy² + c1,  b2 = (⟨x²⟩ − μx²) + (⟨y²⟩ − μy²) + c2,

as `photometric.ssim_from_moments` writes it in PyTorch (the reference the tests hold
these kernels to). Its gradient, for an upstream g and s = SSIM:

    ∂s/∂⟨xy⟩ = 2 a1 / (b1 b2),   ∂s/∂⟨x²⟩ = −s / b2,
    ∂s/∂μx = 2 μy (a2 − a1) / (b1 b2) − 2 μx s (1/b1 − 1/b2).

Each pixel is computed in float64 and rounded once to the moments' dtype. In PyTorch the
map is some fifteen whole-image operations forward and thirty backward, each a pass over
memory; here it is one each way. Every pixel is independent, so the results are the same
at any thread count.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, inline="always")
def _terms(mu_x, mean_xx, mean_xy, mu_y, mean_yy, c1, c2, i):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Pixel i's μx, μy and the map's four factors a1, a2, b1, b2 (module docstring), in
    float64: what the forward divides and the backward differentiates."""
    x, y = np.float64(mu_x[i]), np.float64(mu_y[i])
    a1 = 2.0 * (x * y) + c1
    a2 = 2.0 * (np.float64(mean_xy[i]) - x * y) + c2
    b1 = x * x + y * y + c1
    b2 = (np.float64(mean_xx[i]) - x * x) + (np.float64(mean_yy[i]) - y * y) + c2
    return x, y, a1, a2, b1, b2


@njit(parallel=True, cache=True, nogil=True)
def ssim_forward(
    mu_x: np.ndarray,
    mean_xx: np.ndarray,
    mean_xy: np.ndarray,
    mu_y: np.ndarray,
    mean_yy: np.ndarray,
    c1: float,
    c2: float,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """out [P] = SSIM of every pixel (all arrays flat [P])."""
    for i in prange(out.shape[0]):
        _, _, a1, a2, b1, b2 = _terms(mu_x, mean_xx, mean_xy, mu_y, mean_yy, c1, c2, i)
        out[i] = (a1 * a2) / (b1 * b2)


@njit(parallel=True, cache=True, nogil=True)
def ssim_backward(
    mu_x: np.ndarray,
    mean_xx: np.ndarray,
    mean_xy: np.ndarray,
    mu_y: np.ndarray,
    mean_yy: np.ndarray,
    c1: float,
    c2: float,
    grad: np.ndarray,
    grad_mu_x: np.ndarray,
    grad_mean_xx: np.ndarray,
    grad_mean_xy: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """The upstream gradient `grad` [P] of the map, carried to μx, ⟨x²⟩ and ⟨xy⟩."""
    for i in prange(grad.shape[0]):
        x, y, a1, a2, b1, b2 = _terms(mu_x, mean_xx, mean_xy, mu_y, mean_yy, c1, c2, i)
        den = b1 * b2
        s = (a1 * a2) / den
        g = np.float64(grad[i])
        grad_mean_xy[i] = g * (2.0 * a1 / den)
        grad_mean_xx[i] = -g * (s / b2)
        grad_mu_x[i] = g * (2.0 * y * (a2 - a1) / den - 2.0 * x * s * (1.0 / b1 - 1.0 / b2))

"""SSIM's Gaussian window as compiled kernels (numba): a separable blur with reflect
padding, forward and its adjoint, over the channels of one image in parallel.

Letters: C channels, H×W image, K = 2r + 1 taps.

`kornia.filters.filter2d_separable` with reflect padding is the reference
(tests/losses/test_blur.py holds these kernels to it): each pass pads a row (or column)
by reflection (index −i ↦ i, H − 1 + i ↦ H − 1 − i, the edge not repeated) and correlates
it with the taps, the rows first, then the columns. Sums are accumulated in float64 and
rounded once, in the image's dtype. kornia runs the same filter as a grouped convolution,
which PyTorch's own CPU kernels split into one small convolution per channel (fifteen for
SSIM's five moments of an RGB image, forward and backward): most of SSIM's time in a
training step.

The backward is the adjoint of the same two passes in reverse order: each pass's
correlation transposed (a full convolution into a padded buffer) and the padding's
reflection folded back onto the pixels it copied. Every loop runs in a fixed order, so
the gradients are the same on every run and at any thread count.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, inline="always")
def _reflect(i: int, n: int) -> int:  # pragma: no cover - compiled
    """The pixel that padded position i (counted from the first pixel) copies."""
    if i < 0:
        return -i
    if i > n - 1:
        return 2 * (n - 1) - i
    return i


@njit(parallel=True, cache=True, nogil=True)
def blur(image: np.ndarray, taps: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """out [C, H, W] = the rows of image [C, H, W] correlated with `taps` (float64, K odd,
    r < H and r < W), then the columns, both reflect-padded to the same size."""
    for c in prange(image.shape[0]):
        _blur_channel(image[c], taps, out[c])


@njit(cache=True, nogil=True)
def _blur_channel(image: np.ndarray, taps: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    height, width = image.shape
    r = taps.shape[0] // 2
    padded = np.empty(width + 2 * r)
    rows = np.zeros((height, width))
    for y in range(height):
        for p in range(width + 2 * r):
            padded[p] = image[y, _reflect(p - r, width)]
        row = rows[y]
        for j in range(2 * r + 1):
            k = taps[j]
            for x in range(width):
                row[x] += k * padded[x + j]
    column = np.empty(width)
    for y in range(height):
        column[:] = 0.0
        for j in range(2 * r + 1):
            k = taps[j]
            source = rows[_reflect(y + j - r, height)]
            for x in range(width):
                column[x] += k * source[x]
        for x in range(width):
            out[y, x] = column[x]


@njit(parallel=True, cache=True, nogil=True)
def blur_adjoint(grad: np.ndarray, taps: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """out [C, H, W] = the gradient of Σ grad · blur(image) with respect to image."""
    for c in prange(grad.shape[0]):
        _adjoint_channel(grad[c], taps, out[c])


@njit(cache=True, nogil=True)
def _adjoint_channel(
    grad: np.ndarray, taps: np.ndarray, out: np.ndarray
) -> None:  # pragma: no cover
    height, width = grad.shape
    r = taps.shape[0] // 2
    # The columns' pass transposed: each output row spreads over the padded rows it read,
    # and the padding's rows fold back onto the rows they copied.
    padded_rows = np.zeros((height + 2 * r, width))
    for y in range(height):
        for j in range(2 * r + 1):
            k = taps[j]
            target = padded_rows[y + j]
            for x in range(width):
                target[x] += k * grad[y, x]
    rows = padded_rows[r : r + height].copy()
    for p in range(r):
        rows[_reflect(p - r, height)] += padded_rows[p]
        rows[_reflect(height + p, height)] += padded_rows[height + r + p]
    # The rows' pass transposed, the same way along each row.
    padded = np.empty(width + 2 * r)
    for y in range(height):
        padded[:] = 0.0
        row = rows[y]
        for j in range(2 * r + 1):
            k = taps[j]
            for x in range(width):
                padded[x + j] += k * row[x]
        for p in range(r):
            padded[r + _reflect(p - r, width)] += padded[p]
            padded[r + _reflect(width + p, width)] += padded[width + r + p]
        for x in range(width):
            out[y, x] = padded[x + r]

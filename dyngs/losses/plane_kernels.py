"""The compiled plane regularizers (numba): K-Planes' total variation on the spatial
planes, and temporal smoothness and the L1 pull to a static scene on the time planes
(Fridovich-Keil et al. 2023), forward and backward, each in one pass over every plane.

Letters: F feature channels, R1×R0 cells of a plane (time along R1 on a time plane).

As PyTorch operations (`tv.plane_tv`, `temporal.time_smoothness`,
`temporal.time_l1_to_static`, the reference) each term is a handful of whole-plane
passes per plane forward and twice as many backward: on the demo's field (twelve planes
of 32 channels) about a sixth of a CPU training step, mostly the per-operation cost of
small tensors. Here the forward sums every (plane, channel)'s squared steps, squared
second differences in time and |1 − p| in float64, one job each, and the backward writes
each cell's gradient from the same differences, written out: for a step d = p[i+1] − p[i]
the square's gradient is 2d to p[i+1] and −2d to p[i]; for a second difference
s = p[k] − 2p[k+1] + p[k+2] it is 2s·(1, −2, 1); for |1 − p| it is −sign(1 − p), 0 at 1
(PyTorch's `abs` gradient). The sums are in a fixed order, so a run is the same at every
thread count (tests/losses/test_plane_kernels.py holds them to the reference).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


# Each loop runs along a row (contiguous), so LLVM vectorises it; the sums may be
# reassociated into one partial sum per vector lane, in an order fixed by the compiled
# code, so a run is still the same on every run and at every thread count.
@njit(parallel=True, cache=True, nogil=True, fastmath={"reassoc"})
def spatial_sums(planes: tuple, sums: np.ndarray) -> None:  # pragma: no cover - compiled
    """sums[job] = (Σ squared steps along R1, along R0) of one (plane, channel), jobs
    plane by plane, channel by channel."""
    channels = planes[0].shape[0]
    for job in prange(len(planes) * channels):
        plane = planes[job // channels][job % channels]
        rows, columns = plane.shape
        down = across = 0.0
        for i in range(rows):
            row = plane[i]
            if i + 1 < rows:
                below = plane[i + 1]
                for j in range(columns):
                    step = np.float64(below[j]) - np.float64(row[j])
                    down += step * step
            for j in range(columns - 1):
                step = np.float64(row[j + 1]) - np.float64(row[j])
                across += step * step
        sums[job, 0], sums[job, 1] = down, across


@njit(parallel=True, cache=True, nogil=True)
def spatial_grads(planes: tuple, weights: np.ndarray, grads: tuple) -> None:  # pragma: no cover
    """grads (laid out as planes) of Σ_plane weights[plane, 0]·(Σ squared steps along R1)
    + weights[plane, 1]·(… along R0)."""
    channels = planes[0].shape[0]
    for job in prange(len(planes) * channels):
        index, f = job // channels, job % channels
        plane, grad = planes[index][f], grads[index][f]
        down, across = 2.0 * weights[index, 0], 2.0 * weights[index, 1]
        rows, columns = plane.shape
        acc = np.empty(columns)
        for i in range(rows):
            row = plane[i]
            acc[:] = 0.0
            if i + 1 < rows:
                below = plane[i + 1]
                for j in range(columns):
                    acc[j] -= down * (np.float64(below[j]) - np.float64(row[j]))
            if i > 0:
                above = plane[i - 1]
                for j in range(columns):
                    acc[j] += down * (np.float64(row[j]) - np.float64(above[j]))
            for j in range(columns - 1):
                acc[j] -= across * (np.float64(row[j + 1]) - np.float64(row[j]))
            for j in range(1, columns):
                acc[j] += across * (np.float64(row[j]) - np.float64(row[j - 1]))
            for j in range(columns):
                grad[i, j] = acc[j]


@njit(parallel=True, cache=True, nogil=True, fastmath={"reassoc"})
def temporal_sums(planes: tuple, sums: np.ndarray) -> None:  # pragma: no cover - compiled
    """sums[job] = (Σ squared second differences along time (R1), Σ |1 − p|) of one
    (plane, channel)."""
    channels = planes[0].shape[0]
    for job in prange(len(planes) * channels):
        plane = planes[job // channels][job % channels]
        times, columns = plane.shape
        curve = pull = 0.0
        for k in range(times):
            row = plane[k]
            for j in range(columns):
                pull += abs(1.0 - np.float64(row[j]))
            if k + 2 < times:
                middle, last = plane[k + 1], plane[k + 2]
                for j in range(columns):
                    second = (np.float64(row[j]) - 2.0 * np.float64(middle[j])
                              + np.float64(last[j]))  # fmt: skip
                    curve += second * second
        sums[job, 0], sums[job, 1] = curve, pull


@njit(parallel=True, cache=True, nogil=True)
def temporal_grads(planes: tuple, weights: np.ndarray, grads: tuple) -> None:  # pragma: no cover
    """grads of Σ_plane weights[plane, 0]·(Σ squared second differences in time)
    + weights[plane, 1]·(Σ |1 − p|)."""
    channels = planes[0].shape[0]
    for job in prange(len(planes) * channels):
        index, f = job // channels, job % channels
        plane, grad = planes[index][f], grads[index][f]
        curve, pull = 2.0 * weights[index, 0], weights[index, 1]
        times, columns = plane.shape
        acc = np.empty(columns)
        for k in range(times):
            row = plane[k]
            for j in range(columns):
                acc[j] = -pull * np.sign(1.0 - np.float64(row[j]))
            for first in range(max(k - 2, 0), min(k, times - 3) + 1):  # differences k is in
                a, b, c = plane[first], plane[first + 1], plane[first + 2]
                scale = curve * (-2.0 if first + 1 == k else 1.0)
                for j in range(columns):
                    acc[j] += scale * (np.float64(a[j]) - 2.0 * np.float64(b[j])
                                       + np.float64(c[j]))  # fmt: skip
            for j in range(columns):
                grad[k, j] = acc[j]

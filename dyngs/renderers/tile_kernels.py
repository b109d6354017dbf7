"""The compiled compositing kernels of `cpu-tile` (numba), forward and backward.

Letters: N Gaussians, M tile–Gaussian pairs (`stages.TileBins`), T tiles, H×W image.

Both kernels run over tiles in parallel: thread j takes tiles j, j + T, j + 2T, … of a
busiest-first order, so that T threads share the work evenly (numba's own static split
of a busiest-first range gave one thread most of it: 1.3× on two cores, against 2× this
way). Within a tile they walk its depth-sorted
Gaussians (front to back forward, back to front backward) and, for each, only the pixels
inside its α ≥ 1/255 ellipse: on each row of the tile the ellipse is an interval of
columns, found by solving the quadratic form for x, so a pixel outside it costs nothing,
not even an exponential. Pixels keep their own state (transmittance, sums, the last
Gaussian they took), and a tile stops as soon as every one of its pixels has stopped.

Every decision is the one `cpu-reference` makes, in the same precision (the guard table in
docs/DESIGN.md):
- the exponent ln o − ½ dᵀQd in float64, rounded to the compositing dtype, and α = exp of
  that in the compositing dtype, clamped to ≤ `alpha_max`;
- a pair with α < `alpha_min` is skipped;
- transmittance is the running product of (1 − α) rounded to the compositing dtype,
  multiplied in float64 and rounded to the dtype after each factor (which is what
  `torch.cumprod` does on a CPU); a pixel stops before the first pair after which it
  would fall below `transmittance_min`, and that pair is not drawn;
- a pair's weight is α × (transmittance before it), in the compositing dtype.
Sums over a pixel's pairs are accumulated in float64 and rounded once at the end. The
exponential is the C library's where PyTorch uses its own vectorised one, so α may differ
in the last bit; a pair is decided differently only if its α or transmittance lies within
that bit of a threshold.

Forward keeps what backward needs: each pixel's final transmittance (float64) and the
position of the last pair it drew. Backward walks each pixel's pairs back to front,
recovering the transmittance before each pair by dividing by its (1 − α) (≥ 0.01, since
α ≤ 0.99), as the 3DGS kernels do (Kerbl et al. 2023). Per-pair gradients are written to
a [M, 10] array that one serial pass then sums per Gaussian in a fixed order, so a render
and its gradients are the same on every run whatever the thread schedule.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange, types
from numba.extending import overload

_SKIP_MARGIN = 1e-2
"""Rows are cut to the columns where the exponent is ≥ ln(alpha_min) − this margin, far
below any rounding of the exponent, so the cut never drops a pixel the exact per-pixel
test would keep."""

PAIR_GRADS = 12
"""Columns of the per-pair gradients: ∂/∂(mean x, mean y), ∂/∂(conic a, b, c),
∂/∂ln o, ∂/∂(r, g, b, depth), and Σ over pixels of |∂/∂mean x|, |∂/∂mean y| (AbsGS's
statistic, `RenderOutput.means2d_absgrad`)."""


def _to_dtype(like: np.ndarray, value: float) -> float:  # pragma: no cover - see below
    """`value` rounded to the dtype of the array `like` (the compositing dtype). Compiled
    code uses the overload below, a plain cast decided when the kernel is compiled."""
    return float(like.dtype.type(value))


@overload(_to_dtype, inline="always")
def _to_dtype_compiled(like, value):  # type: ignore[no-untyped-def]  # pragma: no cover
    if isinstance(like, types.Array) and like.dtype == types.float32:
        return lambda like, value: np.float32(value)
    return lambda like, value: np.float64(value)


@njit(cache=True, nogil=True, inline="always")
def _row_range(
    my: float, a: float, b: float, c: float, reach: float, y0: int, y1: int
) -> tuple[int, int]:  # pragma: no cover - compiled
    """The rows [lo, hi] of [y0, y1) whose centres the ellipse a·dx² + 2b·dx·dy + c·dy² ≤
    `reach` reaches: |dy| ≤ √(reach · a / (ac − b²)). Empty when lo > hi."""
    det = a * c - b * b
    if not det > 0.0:
        return y0, y1 - 1
    half = math.sqrt(reach * a / det)
    lo = max(y0, math.ceil(max(my - half - 0.5, y0 - 1.0) - 1e-6))
    hi = min(y1 - 1, math.floor(min(my + half - 0.5, y1 + 1.0) + 1e-6))
    return lo, hi


@njit(cache=True, nogil=True, inline="always")
def _row_span(
    mx: float, my: float, a: float, b: float, c: float, reach: float, y: int, x0: int, x1: int
) -> tuple[int, int, float]:  # pragma: no cover - compiled
    """The columns [lo, hi] of pixel row `y`, within [x0, x1), whose centres can lie where
    a Gaussian's exponent reaches the threshold: a·dx² + 2b·dx·dy + c·dy² ≤ `reach`, solved
    for dx (a > 0: Q is positive definite). Also returns dy. Empty when lo > hi."""
    dy = y + 0.5 - my
    disc = (b * dy) * (b * dy) - a * (c * dy * dy - reach)
    if not disc >= 0.0:
        return 1, 0, dy
    root = math.sqrt(disc)
    left = mx - 0.5 + (-b * dy - root) / a
    right = mx - 0.5 + (-b * dy + root) / a
    if not (right >= x0 - 1.0 and left <= x1 + 1.0):
        return 1, 0, dy
    # Clamped in float first, so that a huge ellipse never overflows the conversion.
    lo = max(x0, math.ceil(max(left, x0 - 1.0) - 1e-6))
    hi = min(x1 - 1, math.floor(min(right, x1 + 1.0) + 1e-6))
    return lo, hi, dy


# The kernels take their inputs grouped, so that each stage's signature stays short:
#   scene  = (means2d [N, 2], conics [N, 3], log_opacity [N], features [N, 4],
#             gaussian [M], tile_start [T], tile_count [T])
#   layout = (tiles_x, tile_size, width, height)
#   limits = (alpha_min, alpha_max, transmittance_min)
# means2d, conics (a, b, c of Q = Σ⁻¹) and ln opacity are float64; features (r, g, b,
# depth) are in the compositing dtype, which every decision is made in.


@njit(cache=True, nogil=True, inline="always")
def _tile_box(tile: int, layout: tuple) -> tuple[int, int, int, int]:  # pragma: no cover
    """Pixel bounds [x0, x1) × [y0, y1) of `tile`, cut to the image."""
    tiles_x, size, width, height = layout
    x0 = (tile % tiles_x) * size
    y0 = (tile // tiles_x) * size
    return x0, y0, min(x0 + size, width), min(y0 + size, height)


@njit(cache=True, nogil=True, inline="always")
def _alpha(
    scratch: np.ndarray, lo: float, conic: tuple, dx: float, dy: float, a_max: float
) -> tuple[float, bool]:  # pragma: no cover - compiled
    """A pair's α in the compositing dtype, min(exp(ln o − ½ dᵀQd), a_max), and whether
    the clamp was active (its gradient is then zero)."""
    a, b, c = conic
    exponent = lo - 0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    alpha = np.exp(_to_dtype(scratch, exponent))
    if alpha > a_max:
        return a_max, True
    return alpha, False


@njit(parallel=True, cache=True, nogil=True)
def composite_forward(
    scene: tuple,
    tile_order: np.ndarray,
    layout: tuple,
    limits: tuple,
    sums: np.ndarray,
    transmittance: np.ndarray,
    last: np.ndarray,
    contribution: np.ndarray,
    work: np.ndarray,
    threads: int,
) -> None:  # pragma: no cover - compiled
    """Composite every tile in `tile_order` front to back, on `threads` threads.

    Writes, for every pixel of those tiles, sums [H, W, 5] (Σ w·(r, g, b, depth, 1), in
    the compositing dtype), transmittance [H, W] (float64, after the last pair drawn) and
    last [H, W] (that pair's position in its tile's list, −1 for none); and, when
    `contribution` has M entries, each pair's Σ w over its tile's pixels. work[i] counts
    tile_order[i]'s pixel visits (pixels inside a Gaussian's row spans, still compositing)
    and the pairs it drew.
    """
    for thread in prange(threads):
        for i in range(thread, tile_order.shape[0], threads):
            visited, drawn = _forward_tile(scene, tile_order[i], layout, limits, sums,
                                           transmittance, last, contribution)  # fmt: skip
            work[i, 0] = visited
            work[i, 1] = drawn


@njit(cache=True, nogil=True)
def _forward_tile(
    scene: tuple,
    tile: int,
    layout: tuple,
    limits: tuple,
    sums: np.ndarray,
    transmittance: np.ndarray,
    last: np.ndarray,
    contribution: np.ndarray,
) -> tuple[int, int]:  # pragma: no cover - compiled
    """One tile of `composite_forward`: its Gaussians front to back, until every pixel
    has stopped. Returns the pixel visits and pairs drawn."""
    features, gaussian, tile_start, tile_count = scene[3], scene[4], scene[5], scene[6]
    x0, y0, x1, y1 = _tile_box(tile, layout)
    pixels = (x1 - x0) * (y1 - y0)
    running = np.ones(pixels)  # float64 product of the rounded (1 − α)
    before = np.ones(pixels, dtype=features.dtype)  # the same, rounded: the dtype's T
    done = np.zeros(pixels, dtype=np.bool_)
    acc = np.zeros((pixels, 5))
    taken = np.full(pixels, -1, dtype=np.int64)
    active = pixels
    visits = pairs = 0
    start = tile_start[tile]
    for k in range(tile_count[tile]):
        if active == 0:
            break
        drawn, stopped, seen, took = _forward_gaussian(
            scene, gaussian[start + k], k, (x0, y0, x1, y1), limits, running, before, done,
            acc, taken,
        )  # fmt: skip
        active -= stopped
        visits += seen
        pairs += took
        if contribution.shape[0] > 0:
            contribution[start + k] = drawn
    for y in range(y0, y1):
        for x in range(x0, x1):
            p = (y - y0) * (x1 - x0) + x - x0
            for j in range(5):
                sums[y, x, j] = acc[p, j]
            transmittance[y, x] = running[p]
            last[y, x] = taken[p]
    return visits, pairs


# Inlined: a call would pass a dozen arrays, and numba counts references on each of them,
# which cost more than drawing a small Gaussian (the demo's frames: 7.1 → 5.2 ms, 1 thread).
@njit(cache=True, nogil=True, inline="always")
def _forward_gaussian(
    scene: tuple,
    g: int,
    k: int,
    box: tuple,
    limits: tuple,
    running: np.ndarray,
    before: np.ndarray,
    done: np.ndarray,
    acc: np.ndarray,
    taken: np.ndarray,
) -> tuple[float, int, int, int]:  # pragma: no cover - compiled
    """Draw Gaussian `g` (position `k` in the tile's list) into the tile's pixel state;
    returns Σ w over the pixels it drew, how many pixels stopped at it, how many it
    visited and how many it drew."""
    means2d, conics, log_opacity, features = scene[0], scene[1], scene[2], scene[3]
    x0, y0, x1, y1 = box
    scratch = features  # the dtype to round to
    a_min = _to_dtype(scratch, limits[0])
    a_max = _to_dtype(scratch, limits[1])
    t_min = _to_dtype(scratch, limits[2])
    mx, my, lo = means2d[g, 0], means2d[g, 1], log_opacity[g]
    conic = (conics[g, 0], conics[g, 1], conics[g, 2])
    reach = 2.0 * (lo - math.log(limits[0]) + _SKIP_MARGIN)
    drawn, stopped, visits, pairs = 0.0, 0, 0, 0
    if not reach > 0.0:
        return drawn, stopped, visits, pairs
    f0, f1, f2, f3 = features[g, 0], features[g, 1], features[g, 2], features[g, 3]
    row_lo, row_hi = _row_range(my, conic[0], conic[1], conic[2], reach, y0, y1)
    for y in range(row_lo, row_hi + 1):
        col_lo, col_hi, dy = _row_span(mx, my, conic[0], conic[1], conic[2], reach, y, x0, x1)
        row = (y - y0) * (x1 - x0) - x0
        for x in range(col_lo, col_hi + 1):
            p = row + x
            if done[p]:
                continue
            visits += 1
            alpha, _ = _alpha(scratch, lo, conic, x + 0.5 - mx, dy, a_max)
            if alpha < a_min:
                continue
            after = running[p] * _to_dtype(scratch, 1.0 - alpha)
            if _to_dtype(scratch, after) < t_min:
                done[p] = True
                stopped += 1
                continue
            w = alpha * before[p]
            acc[p, 0] += w * f0
            acc[p, 1] += w * f1
            acc[p, 2] += w * f2
            acc[p, 3] += w * f3
            acc[p, 4] += w
            drawn += w
            pairs += 1
            running[p] = after
            before[p] = _to_dtype(scratch, after)
            taken[p] = k
    return drawn, stopped, visits, pairs


@njit(parallel=True, cache=True, nogil=True)
def composite_backward(
    scene: tuple,
    tile_order: np.ndarray,
    layout: tuple,
    limits: tuple,
    grad_sums: np.ndarray,
    transmittance: np.ndarray,
    last: np.ndarray,
    pair_grads: np.ndarray,
    threads: int,
) -> None:  # pragma: no cover - compiled
    """The gradient of Σ over pixels of grad_sums · sums, per tile–Gaussian pair, on
    `threads` threads.

    grad_sums [H, W, 5] is float64; transmittance and last are what `composite_forward`
    left. Writes pair_grads [M, `PAIR_GRADS`] for every pair of the tiles in `tile_order`.
    With w = α T and s = ∂L/∂(Σ w f) · f for a pixel, ∂L/∂α of pair k is
    T_k (s_k − R_k), where R_k = Σ_{j>k} s_j w_j / T_{k+1} is carried back to front:
    R_{k−1} = s_k α_k + (1 − α_k) R_k.
    """
    for thread in prange(threads):
        for i in range(thread, tile_order.shape[0], threads):
            _backward_tile(scene, tile_order[i], layout, limits, grad_sums, transmittance,
                           last, pair_grads)  # fmt: skip


@njit(cache=True, nogil=True)
def _backward_tile(
    scene: tuple,
    tile: int,
    layout: tuple,
    limits: tuple,
    grad_sums: np.ndarray,
    transmittance: np.ndarray,
    last: np.ndarray,
    pair_grads: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """One tile of `composite_backward`: its Gaussians back to front, from the deepest
    pair any pixel drew."""
    gaussian, tile_start, tile_count = scene[4], scene[5], scene[6]
    x0, y0, x1, y1 = _tile_box(tile, layout)
    pixels = (x1 - x0) * (y1 - y0)
    trans = np.empty(pixels)
    rest = np.zeros(pixels)
    taken = np.empty(pixels, dtype=np.int64)
    upstream = np.empty((pixels, 5))
    for y in range(y0, y1):
        for x in range(x0, x1):
            p = (y - y0) * (x1 - x0) + x - x0
            trans[p] = transmittance[y, x]
            taken[p] = last[y, x]
            for j in range(5):
                upstream[p, j] = grad_sums[y, x, j]
    start = tile_start[tile]
    deepest = taken.max() if pixels > 0 else -1
    pair_grads[start + deepest + 1 : start + tile_count[tile]] = 0.0
    for k in range(deepest, -1, -1):
        grad = pair_grads[start + k]
        grad[:] = 0.0
        _backward_gaussian(scene, gaussian[start + k], k, (x0, y0, x1, y1), limits, trans,
                           rest, taken, upstream, grad)  # fmt: skip


@njit(cache=True, nogil=True, inline="always")
def _backward_gaussian(
    scene: tuple,
    g: int,
    k: int,
    box: tuple,
    limits: tuple,
    trans: np.ndarray,
    rest: np.ndarray,
    taken: np.ndarray,
    upstream: np.ndarray,
    grad: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Add Gaussian `g`'s gradients over the tile's pixels to `grad`, and step each
    pixel's transmittance and R back past it."""
    means2d, conics, log_opacity, features = scene[0], scene[1], scene[2], scene[3]
    x0, y0, x1, y1 = box
    scratch = features  # the dtype to round to
    a_min = _to_dtype(scratch, limits[0])
    a_max = _to_dtype(scratch, limits[1])
    mx, my, lo = means2d[g, 0], means2d[g, 1], log_opacity[g]
    a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
    reach = 2.0 * (lo - math.log(limits[0]) + _SKIP_MARGIN)
    if not reach > 0.0:
        return
    f0, f1, f2, f3 = features[g, 0], features[g, 1], features[g, 2], features[g, 3]
    row_lo, row_hi = _row_range(my, a, b, c, reach, y0, y1)
    for y in range(row_lo, row_hi + 1):
        col_lo, col_hi, dy = _row_span(mx, my, a, b, c, reach, y, x0, x1)
        row = (y - y0) * (x1 - x0) - x0
        for x in range(col_lo, col_hi + 1):
            p = row + x
            if k > taken[p]:
                continue
            dx = x + 0.5 - mx
            alpha, clamped = _alpha(scratch, lo, (a, b, c), dx, dy, a_max)
            if alpha < a_min:
                continue
            keep = float(_to_dtype(scratch, 1.0 - alpha))
            t_before = trans[p] / keep
            al = float(alpha)
            w = al * t_before
            u = upstream[p]
            s = u[0] * f0 + u[1] * f1 + u[2] * f2 + u[3] * f3 + u[4]
            for j in range(4):
                grad[6 + j] += w * u[j]
            d_alpha = t_before * (s - rest[p])
            rest[p] = s * al + keep * rest[p]
            trans[p] = t_before
            if not clamped:
                d_exp = d_alpha * al
                g_mx, g_my = d_exp * (a * dx + b * dy), d_exp * (b * dx + c * dy)
                grad[0] += g_mx
                grad[1] += g_my
                grad[10] += abs(g_mx)
                grad[11] += abs(g_my)
                grad[2] -= 0.5 * d_exp * dx * dx
                grad[3] -= d_exp * dx * dy
                grad[4] -= 0.5 * d_exp * dy * dy
                grad[5] += d_exp


@njit(cache=True, nogil=True)
def sum_pairs(
    gaussian: np.ndarray, per_pair: np.ndarray, per_gaussian: np.ndarray
) -> None:  # pragma: no cover - compiled
    """per_gaussian[gaussian[m]] += per_pair[m] for every pair m, in order (one thread, so
    the sums are the same on every run)."""
    for m in range(gaussian.shape[0]):
        g = gaussian[m]
        for j in range(per_pair.shape[1]):
            per_gaussian[g, j] += per_pair[m, j]


@njit(cache=True, nogil=True)
def bin_pairs(
    order: np.ndarray, lo: np.ndarray, hi: np.ndarray, tile_size: int, tiles_x: int, tiles: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """`stages.bin_tiles` as a counting sort: the Gaussians `order` (depth order) with
    inclusive pixel boxes [lo, hi] (columns, rows) → (Gaussian of each pair, first pair of
    each tile, pairs per tile). One pass counts each tile's pairs, a second deals the
    Gaussians out in depth order, so every tile's list comes out front to back, exactly as
    the stable sort by tile of the reference leaves it."""
    count = np.zeros(tiles, dtype=np.int64)
    for v in range(order.shape[0]):
        for ty in range(lo[v, 1] // tile_size, hi[v, 1] // tile_size + 1):
            for tx in range(lo[v, 0] // tile_size, hi[v, 0] // tile_size + 1):
                count[ty * tiles_x + tx] += 1
    start = np.empty(tiles, dtype=np.int64)
    total = 0
    for t in range(tiles):
        start[t] = total
        total += count[t]
    gaussian = np.empty(total, dtype=np.int64)
    fill = start.copy()
    for v in range(order.shape[0]):
        for ty in range(lo[v, 1] // tile_size, hi[v, 1] // tile_size + 1):
            for tx in range(lo[v, 0] // tile_size, hi[v, 0] // tile_size + 1):
                t = ty * tiles_x + tx
                gaussian[fill[t]] = order[v]
                fill[t] += 1
    return gaussian, start, count

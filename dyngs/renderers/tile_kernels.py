"""The compiled compositing kernels of `cpu-tile` (numba), forward and backward.

Letters: N Gaussians, M tile–Gaussian pairs (`stages.TileBins`), T tiles, H×W image.

Both kernels run over tiles in parallel: thread j takes tiles j, j + T, j + 2T, … of a
busiest-first order, so that T threads share the work evenly (numba's own static split
of a busiest-first range gave one thread most of it: 1.3× on two cores, against 2× this
way). Within a tile they walk its depth-sorted Gaussians (front to back forward, back to
front backward) and, for each, every pixel of the rows and 8-column blocks its
α ≥ 1/255 ellipse reaches. Those pixels run one straight-line body, every branch of the
per-pixel rule written as a select, which LLVM compiles to vector instructions (eight
float64 lanes): a pixel outside the ellipse costs a lane rather than a mispredicted
branch, and a small Gaussian (most of a trained model) no longer pays a per-row set-up
that outweighs its few pixels. Pixels keep their own state (transmittance, sums, the last
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
Sums over a pixel's pairs are accumulated in float64 and rounded once at the end. In
float32 the exponential is the correctly rounded one (`_exp_nonpositive`, a polynomial
that vectorises), where PyTorch uses its own vectorised `expf`, within an ulp of it; so α
may differ in the last bit, and a pair is decided differently only if its α or
transmittance lies within that bit of a threshold. In float64 it is libm's `exp`.

Forward keeps what backward needs: each pixel's final transmittance (float64) and the
position of the last pair it drew, as the 3DGS kernels do (Kerbl et al. 2023), and the
unclamped α of every cell each pair ran (in the compositing dtype), so that backward reads
the exponentials back instead of evaluating them again (docs/RENDERER.md measures the
trade: backward more than twice as fast, forward somewhat slower for the writes). Backward
walks each pixel's pairs back to front, recovering the transmittance before each pair by
dividing by its (1 − α) (≥ 0.01, since α ≤ 0.99). Per-pair gradients are written to a
[M, 12] array that one serial pass then sums per Gaussian in a fixed order, so a render
and its gradients are the same on every run whatever the thread schedule.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange, types
from numba.extending import overload

from dyngs.compiled import noalias_option
from dyngs.renderers.project_kernels import pixel_span

_NOALIAS = noalias_option()

_SKIP_MARGIN = 1e-2
"""A Gaussian is drawn on the rows where its exponent can reach ln(alpha_min) − this
margin, far below any rounding of the exponent, so the cut never drops a pixel the exact
per-pixel test would keep."""

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


LANES = 8
"""Columns of a block: a tile's pixel state is laid out block by block, each block LANES
columns wide (8 float64 lanes fill one AVX-512 register), and within a block row by row,
so the cells of a Gaussian's rows within one block are one contiguous run (`_cell`).
Columns past the image in the last block are padding, stopped from the start."""


@njit(cache=True, nogil=True)
def tile_cells(size: int) -> int:  # pragma: no cover - compiled (also called from Python)
    """The cells of a whole tile of `size`² pixels, padding included: the most α any one
    pair keeps for backward (`kept`, below)."""
    return -(-size // LANES) * LANES * size


_LN2_HI = 0.6931471803691238  # ln 2 in two parts (Cody and Waite 1980): n·_LN2_HI is exact
_LN2_LO = 1.9082149292705877e-10


# Not inlined by numba but by LLVM: a numba-level inline would take the instructions into
# the caller's fastmath flags (the backward kernel reassociates its sums), and this
# function's rounding must stay as written. The same for `_exponent`. `contract` lets LLVM
# fuse each multiply-add of the polynomial into one FMA, rounded once (the test in
# tests/renderers/test_cpu_tile.py holds the result to the correctly rounded float32).
@njit(cache=True, nogil=True, fastmath={"contract"})
def _exp_nonpositive(x: float) -> float:  # pragma: no cover - compiled
    """exp(x) in float64 for −103 ≤ x ≤ 0 (x is clamped to that range), to ~1e-15
    relative, in straight-line arithmetic that vectorises (libm's `exp` is a call, one
    lane at a time). Range reduction x = n ln 2 + r with |r| ≤ ½ ln 2; eʳ by its Taylor
    polynomial of degree 11 (remainder (½ ln 2)¹²/12! < 1e-14); 2ⁿ written straight into
    a float64's exponent bits. Rounded to float32 it is the correctly rounded exponential
    wherever float32 is normal (x ≥ −87; tests/renderers/test_cpu_tile.py)."""
    x = max(min(x, 0.0), -103.0)
    n = math.floor(x * 1.4426950408889634 + 0.5)  # x / ln 2, to the nearest integer
    r = (x - n * _LN2_HI) - n * _LN2_LO
    p = 1.0 / 39916800.0
    p = p * r + 1.0 / 3628800.0
    p = p * r + 1.0 / 362880.0
    p = p * r + 1.0 / 40320.0
    p = p * r + 1.0 / 5040.0
    p = p * r + 1.0 / 720.0
    p = p * r + 1.0 / 120.0
    p = p * r + 1.0 / 24.0
    p = p * r + 1.0 / 6.0
    p = p * r + 0.5
    p = p * r + 1.0
    p = p * r + 1.0
    return p * np.int64((n + 1023) << 52).view(np.float64)  # 2ⁿ, −149 ≤ n ≤ 0


@njit(cache=True, nogil=True)
def _exponent(
    lo: float, a: float, b: float, c: float, dx: float, dy: float
) -> float:  # pragma: no cover - compiled
    """ln o − ½ dᵀQd in float64, in the reference's order of operations."""
    return lo - 0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy


def _exp(like: np.ndarray, exponent: float) -> float:  # pragma: no cover - see below
    """exp of `exponent` rounded to the compositing dtype (the dtype of the array `like`),
    in that dtype. Compiled code uses the overload below."""
    rounded = like.dtype.type(exponent)
    return float(like.dtype.type(np.exp(rounded)))


@njit(cache=True, nogil=True, inline="always")
def _expf(exponent: float) -> np.float32:  # pragma: no cover - compiled
    """The exponent rounded to float32, its exponential correctly rounded to float32
    (PyTorch's vectorised expf, which the reference uses, is within an ulp of it)."""
    return np.float32(_exp_nonpositive(np.float64(np.float32(exponent))))


@overload(_exp, inline="always")
def _exp_compiled(like, exponent):  # type: ignore[no-untyped-def]  # pragma: no cover
    if isinstance(like, types.Array) and like.dtype == types.float32:
        return lambda like, exponent: _expf(exponent)
    return lambda like, exponent: np.exp(np.float64(exponent))


@njit(cache=True, nogil=True, inline="always")
def _reach(
    m: float, along: float, det: float, reach: float, lo: int, hi: int
) -> tuple[int, int]:  # pragma: no cover - compiled
    """The pixels [first, last] of [lo, hi) whose centres an ellipse
    a·dx² + 2b·dx·dy + c·dy² ≤ `reach` reaches along one axis: |d| ≤ √(reach·along/det),
    `along` the conic entry of the other axis (a for rows, c for columns) and
    det = ac − b². Empty when first > last; all of [lo, hi) when det is not positive."""
    if not det > 0.0:
        return lo, hi - 1
    half = math.sqrt(reach * along / det)
    first = max(lo, math.ceil(max(m - half - 0.5, lo - 1.0) - 1e-6))
    last = min(hi - 1, math.floor(min(m + half - 0.5, hi + 1.0) + 1e-6))
    return first, last


# The kernels take their inputs grouped, so that each stage's signature stays short:
#   scene  = (means2d [N, 2], conics [N, 3], log_opacity [N], features [N, 4],
#             gaussian [M], tile_start [T], tile_count [T])
#   layout = (tiles_x, tile_size, width, height)
#   limits = (alpha_min, alpha_max, transmittance_min)
#   kept   = (transmittance [H, W], last [H, W], alphas [threads, A], feet [M, 5]): what
#            forward keeps for backward, empty when no backward will follow (but alphas:
#            then one tile's cells a thread, each pair's α written over the last's, as an
#            unconditional store is far cheaper than a masked one on AMD's cores). Pair m's
#            footprint is feet[m, 1:] = (r0, r1, b0, b1) (`_footprint`, whose square roots
#            and divisions backward need not repeat), and its α over the cells it ran,
#            block by block, row by row, are alphas[j, feet[m, 0]:], j the thread that
#            composited its tile (both kernels deal tiles to threads alike). Each thread
#            fills its row downwards from the end, pair after pair: so backward, taking a
#            tile's pairs back to front, reads them in ascending order, which the hardware
#            prefetches (front to back, backward was no faster for them wherever they
#            outgrew the caches), and what a render writes is always the end of the row
#            (`cpu_tile._AlphaStore` reuses the arrays).
# means2d, conics (a, b, c of Q = Σ⁻¹) and ln opacity are float64; features (r, g, b,
# depth) are in the compositing dtype, which every decision is made in.
#
# Inside a tile, each quantity of the pixel state is its own 1D array over the tile's
# cells, allocated separately: LLVM vectorises a loop over cells only when it can tell the
# arrays apart (one 2D array's rows it cannot), and indices it can prove non-negative
# (hence the unsigned cell index: numba wraps negative ones). Cell (row r, column i) is
# (i // LANES) · rows · LANES + r · LANES + i % LANES.


@njit(cache=True, nogil=True, inline="always")
def _tile_box(tile: int, layout: tuple) -> tuple[int, int, int, int]:  # pragma: no cover
    """Pixel bounds [x0, x1) × [y0, y1) of `tile`, cut to the image."""
    tiles_x, size, width, height = layout
    x0 = (tile % tiles_x) * size
    y0 = (tile // tiles_x) * size
    return x0, y0, min(x0 + size, width), min(y0 + size, height)


@njit(cache=True, nogil=True, inline="always")
def _thresholds(like: np.ndarray, limits: tuple) -> tuple:  # pragma: no cover - compiled
    """alpha_min, alpha_max and transmittance_min rounded to the compositing dtype (that of
    the array `like`), which every decision is made in."""
    return _to_dtype(like, limits[0]), _to_dtype(like, limits[1]), _to_dtype(like, limits[2])


@njit(cache=True, nogil=True, inline="always")
def _cell(r: int, i: int, rows: int) -> int:  # pragma: no cover - compiled
    """The cell of row r, column i (both counted within the tile) of a tile of `rows`."""
    return (i // LANES) * rows * LANES + r * LANES + i % LANES


@njit(cache=True, nogil=True, inline="always")
def _centres(x0: int, y0: int, width: int, rows: int) -> tuple:  # pragma: no cover
    """The pixel centres (x + ½, y + ½) of a tile's cells (padding included), as two
    float64 arrays."""
    cells = -(-width // LANES) * LANES * rows
    xs, ys = np.empty(cells), np.empty(cells)
    for r in range(rows):
        for i in range(-(-width // LANES) * LANES):
            xs[_cell(r, i, rows)] = (x0 + i) + 0.5
            ys[_cell(r, i, rows)] = (y0 + r) + 0.5
    return xs, ys


@njit(cache=True, nogil=True, inline="always")
def _footprint(
    scene: tuple, g: int, box: tuple, log_alpha_min: float
) -> tuple[float, float, float, float, float, float, int, int, int, int]:  # pragma: no cover
    """Gaussian g's mean, ln opacity and conic, the rows [r0, r1] of the tile `box` and
    its blocks of columns [b0, b1] (both counted within the tile) that its α ≥ alpha_min
    ellipse, widened by `_SKIP_MARGIN` in the exponent, reaches; r0 > r1 when none. The
    per-pixel test decides every pixel of those cells exactly; the cut only saves work."""
    means2d, conics, log_opacity = scene[0], scene[1], scene[2]
    x0, y0, x1, y1 = box
    mx, my, lo = means2d[g, 0], means2d[g, 1], log_opacity[g]
    a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
    reach = 2.0 * (lo - log_alpha_min + _SKIP_MARGIN)
    if not reach > 0.0:
        return mx, my, lo, a, b, c, 1, 0, 1, 0
    det = a * c - b * b
    c0, c1 = _reach(mx, c, det, reach, x0, x1)
    if c0 > c1:
        return mx, my, lo, a, b, c, 1, 0, 1, 0
    r0, r1 = _reach(my, a, det, reach, y0, y1)
    return mx, my, lo, a, b, c, r0 - y0, r1 - y0, (c0 - x0) // LANES, (c1 - x0) // LANES


@njit(cache=True, nogil=True, inline="always")
def _footprint_cells(foot: tuple) -> int:  # pragma: no cover - compiled
    """The cells a pair runs, given its `_footprint`: its rows × LANES in each block."""
    r0, r1, b0, b1 = foot[6], foot[7], foot[8], foot[9]
    return max(r1 + 1 - r0, 0) * LANES * max(b1 + 1 - b0, 0)


@njit(parallel=True, cache=True, nogil=True)
def composite_forward(
    scene: tuple,
    deal: tuple,
    layout: tuple,
    limits: tuple,
    sums: np.ndarray,
    kept: tuple,
    contribution: np.ndarray,
    work: np.ndarray,
    threads: int,
) -> None:  # pragma: no cover - compiled
    """Composite the tiles of `deal` front to back, on `threads` threads: deal (order,
    bounds) gives thread j the tiles order[bounds[j]:bounds[j + 1]].

    Writes, for every pixel of those tiles, sums [H, W, 5] (Σ w·(r, g, b, depth, 1), in
    the compositing dtype), transmittance [H, W] (float64, after the last pair drawn) and
    last [H, W] (that pair's position in its tile's list, −1 for none), unless both are
    empty (a render no backward will follow); and, when
    `contribution` has M entries, each pair's Σ w over its tile's pixels. work[i] counts
    order[i]'s lanes (the cells its Gaussians' rows and blocks cover, each evaluated
    whether or not it is inside the ellipse) and the pairs it drew.
    """
    order, bounds = deal
    for thread in prange(threads):
        stored = kept[2].shape[1] if kept[3].shape[0] > 0 else 0  # where its α start
        for i in range(bounds[thread], bounds[thread + 1]):
            lanes, drawn, stored = _forward_tile(scene, order[i], layout, limits, sums,
                                                 kept, contribution, thread, stored)  # fmt: skip
            work[i, 0] = lanes
            work[i, 1] = drawn


@njit(cache=True, nogil=True)
def _forward_tile(
    scene: tuple,
    tile: int,
    layout: tuple,
    limits: tuple,
    sums: np.ndarray,
    kept: tuple,
    contribution: np.ndarray,
    thread: int,
    stored: int,
) -> tuple[int, int, int]:  # pragma: no cover - compiled
    """One tile of `composite_forward`: its Gaussians front to back, until every pixel
    has stopped, their α kept in alphas[thread] below `stored`. Returns the lanes run,
    the pairs drawn and where the α the thread's row holds now start."""
    x0, y0, x1, y1 = _tile_box(tile, layout)
    width, rows = x1 - x0, y1 - y0
    centres = _centres(x0, y0, width, rows)
    cells = centres[0].shape[0]
    # The float64 product of the rounded (1 − α), negated once the pixel has stopped (it
    # is at least ~1e-6 while drawing, since it stops below 1e-4 and α ≤ 0.99).
    running = np.ones(cells)
    for r in range(rows):
        for i in range(width, -(-width // LANES) * LANES):
            running[_cell(r, i, rows)] = -1.0
    acc = (np.zeros(cells), np.zeros(cells), np.zeros(cells), np.zeros(cells), np.zeros(cells))
    taken = np.full(cells, -1, dtype=np.int64)
    weights = np.zeros(cells)  # w of the current pair, per cell
    box = (x0, y0, x1, y1)
    transmittance, last, alphas, feet = kept
    keep = transmittance.shape[0] > 0  # the state backward needs, when it will run
    lanes, pairs, stored = _forward_list(scene, tile, box, limits, centres, running, acc,
                                         taken, weights, contribution, alphas[thread], feet,
                                         stored)  # fmt: skip
    for r in range(rows):
        for i in range(width):
            p = _cell(r, i, rows)
            for j in range(5):
                sums[y0 + r, x0 + i, j] = acc[j][p]
            if keep:
                transmittance[y0 + r, x0 + i] = abs(running[p])
                last[y0 + r, x0 + i] = taken[p]
    return lanes, pairs, stored


# One call a tile, with the tile's pixel state as arguments: `noalias` tells LLVM that
# no two of them overlap (numba marks every array argument so; each is its own allocation
# or a distinct input), which it cannot know of arrays allocated in the caller, so the
# per-cell loop no longer checks the arrays against each other before every run.
@njit(cache=True, nogil=True, **_NOALIAS)
def _forward_list(
    scene: tuple,
    tile: int,
    box: tuple,
    limits: tuple,
    centres: tuple,
    running: np.ndarray,
    acc: tuple,
    taken: np.ndarray,
    weights: np.ndarray,
    contribution: np.ndarray,
    alphas: np.ndarray,
    feet: np.ndarray,
    stored: int,
) -> tuple[int, int, int]:  # pragma: no cover - compiled
    """The tile's Gaussians front to back, until every pixel has stopped, each one's α
    kept in `alphas` just below the one before, from `stored` down: the lanes run, pairs
    drawn and where the kept α now start."""
    gaussian, tile_start, tile_count = scene[4], scene[5], scene[6]
    x0, y0, x1, y1 = box
    log_alpha_min = math.log(limits[0])
    active = (y1 - y0) * (x1 - x0)
    lanes = pairs = 0
    start = tile_start[tile]
    keep = feet.shape[0] > 0
    for k in range(tile_count[tile]):
        if active == 0:
            break
        g = gaussian[start + k]
        foot = _footprint(scene, g, box, log_alpha_min)
        if keep:
            stored -= _footprint_cells(foot)
            feet[start + k, 0] = stored
            feet[start + k, 1], feet[start + k, 2] = foot[6], foot[7]
            feet[start + k, 3], feet[start + k, 4] = foot[8], foot[9]
        drawn, stopped, ran, took = _forward_gaussian(
            scene, g, k, foot, box, limits, centres, (running, acc, taken, weights),
            contribution.shape[0] > 0, (alphas, stored),
        )  # fmt: skip
        active -= stopped
        lanes += ran
        pairs += took
        if contribution.shape[0] > 0:
            contribution[start + k] = drawn
    return lanes, pairs, stored


# Inlined: a call would pass a dozen arrays, and numba counts references on each of them,
# which cost more than drawing a small Gaussian (the demo's frames: 7.1 → 5.2 ms, 1 thread).
@njit(cache=True, nogil=True, inline="always")
def _forward_gaussian(
    scene: tuple,
    g: int,
    k: int,
    foot: tuple,
    box: tuple,
    limits: tuple,
    centres: tuple,
    state: tuple,
    measure: bool,
    kept: tuple,
) -> tuple[float, int, int, int]:  # pragma: no cover - compiled
    """Draw Gaussian `g` (position `k` in the tile's list; `foot` its `_footprint`) into
    the tile's pixel state (running, acc, taken, weights), and each cell's unclamped α into
    kept = (alphas, first). Returns Σ w over the pixels it drew (when `measure`), how many
    pixels stopped at it, how many cells it ran and how many pixels it drew.

    Within each block of columns it reaches, the cells of its rows are one run, and every
    cell runs the same straight-line code (each branch of the per-pixel rule a select,
    each store writing back the new or the old value), which LLVM turns into vector
    instructions: a cell outside the ellipse costs a lane, not a mispredicted branch."""
    features = scratch = scene[3]  # scratch: the dtype to round to
    a_min, a_max, t_min = _thresholds(scratch, limits)
    zero = _to_dtype(scratch, 0.0)
    mx, my, lo, a, b, c, r0, r1, b0, b1 = foot
    f0, f1, f2, f3 = features[g, 0], features[g, 1], features[g, 2], features[g, 3]
    running, (acc0, acc1, acc2, acc3, acc4), taken, weights = state
    (alphas, stored), (xs, ys) = kept, centres
    column_cells = (box[3] - box[1]) * LANES  # the cells of one block
    run = max(r1 + 1 - r0, 0) * LANES
    drawn = 0.0
    stopped = pairs = 0
    for block in range(b0, b1 + 1):
        first = block * column_cells + r0 * LANES
        here = stored + (block - b0) * run
        for j in range(run):
            p = np.uint64(first + j)
            raw = _exp(scratch, _exponent(lo, a, b, c, xs[p] - mx, ys[p] - my))
            alphas[np.uint64(here + j)] = raw
            alpha = min(raw, a_max)
            t = running[p]
            live = (t > 0.0) & (alpha >= a_min)
            after = t * _to_dtype(scratch, 1.0 - alpha)
            stop = live & (_to_dtype(scratch, after) < t_min)
            draw = live & (not stop)
            w = alpha * _to_dtype(scratch, t) if draw else zero  # α × T, T in the dtype
            acc0[p] += w * f0
            acc1[p] += w * f1
            acc2[p] += w * f2
            acc3[p] += w * f3
            acc4[p] += w
            weights[p] = w
            running[p] = after if draw else (-t if stop else t)
            taken[p] = k if draw else taken[p]
            stopped += stop
            pairs += draw
        if measure:
            for j in range(run):
                drawn += weights[first + j]
    return drawn, stopped, _footprint_cells(foot), pairs


@njit(parallel=True, cache=True, nogil=True)
def composite_backward(
    scene: tuple,
    deal: tuple,
    layout: tuple,
    limits: tuple,
    grad_sums: np.ndarray,
    kept: tuple,
    pair_grads: np.ndarray,
    threads: int,
) -> None:  # pragma: no cover - compiled
    """The gradient of Σ over pixels of grad_sums · sums, per tile–Gaussian pair, on
    `threads` threads.

    grad_sums [H, W, 5] is in any float dtype (read as float64); transmittance and last
    are what `composite_forward` left. Writes pair_grads [M, `PAIR_GRADS`] for every pair
    of the tiles in `deal`, each on the thread the forward drew it on.
    With w = α T and s = ∂L/∂(Σ w f) · f for a pixel, ∂L/∂α of pair k is
    T_k (s_k − R_k), where R_k = Σ_{j>k} s_j w_j / T_{k+1} is carried back to front:
    R_{k−1} = s_k α_k + (1 − α_k) R_k.
    """
    order, bounds = deal
    for thread in prange(threads):
        for i in range(bounds[thread], bounds[thread + 1]):
            _backward_tile(scene, order[i], layout, limits, grad_sums, kept,
                           pair_grads, thread)  # fmt: skip


@njit(cache=True, nogil=True)
def _backward_tile(
    scene: tuple,
    tile: int,
    layout: tuple,
    limits: tuple,
    grad_sums: np.ndarray,
    kept: tuple,
    pair_grads: np.ndarray,
    thread: int,
) -> None:  # pragma: no cover - compiled
    """One tile of `composite_backward` on `thread`: its Gaussians back to front, from
    the deepest pair any pixel drew."""
    tile_start, tile_count = scene[5], scene[6]
    transmittance, last, alphas, feet = kept
    x0, y0, x1, y1 = _tile_box(tile, layout)
    width, rows = x1 - x0, y1 - y0
    centres = _centres(x0, y0, width, rows)
    cells = centres[0].shape[0]
    trans = np.ones(cells)
    rest = np.zeros(cells)
    taken = np.full(cells, -1, dtype=np.int64)  # the padding draws nothing
    upstream = (np.zeros(cells), np.zeros(cells), np.zeros(cells), np.zeros(cells),
                np.zeros(cells))  # fmt: skip
    for r in range(rows):
        for i in range(width):
            p = _cell(r, i, rows)
            trans[p] = transmittance[y0 + r, x0 + i]
            taken[p] = last[y0 + r, x0 + i]
            for j in range(5):
                upstream[j][p] = grad_sums[y0 + r, x0 + i, j]
    start = tile_start[tile]
    deepest = taken.max() if cells > 0 else -1
    pair_grads[start + deepest + 1 : start + tile_count[tile]] = 0.0
    _backward_list(scene, tile, (x0, y0, x1, y1), limits, centres, trans, rest, taken,
                   upstream, pair_grads, deepest, alphas[thread], feet)  # fmt: skip


# Two flags make the per-cell loop vectorise: division without numba's zero check (1 − α
# is at least 0.01), and sums over a pair's cells that LLVM may reassociate into one
# partial sum per vector lane. That order is fixed by the compiled code, so gradients are
# still the same on every run and at every thread count; they differ from a sum in cell
# order only in rounding. `noalias` as for `_forward_list`.
@njit(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc"}, **_NOALIAS)
def _backward_list(
    scene: tuple,
    tile: int,
    box: tuple,
    limits: tuple,
    centres: tuple,
    trans: np.ndarray,
    rest: np.ndarray,
    taken: np.ndarray,
    upstream: tuple,
    pair_grads: np.ndarray,
    deepest: int,
    alphas: np.ndarray,
    feet: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """The tile's Gaussians back to front, from the deepest pair any pixel drew."""
    gaussian, start = scene[4], scene[5][tile]
    for k in range(deepest, -1, -1):
        _backward_gaussian(scene, gaussian[start + k], k, box, limits, centres,
                           (trans, rest, taken, upstream), pair_grads[start + k],
                           (alphas[feet[start + k, 0] :], feet[start + k]))  # fmt: skip


@njit(cache=True, nogil=True, inline="always")
def _backward_gaussian(
    scene: tuple,
    g: int,
    k: int,
    box: tuple,
    limits: tuple,
    centres: tuple,
    state: tuple,
    grad: np.ndarray,
    kept: tuple,
) -> None:  # pragma: no cover - compiled
    """Write Gaussian `g`'s gradients over the tile's pixels to grad [`PAIR_GRADS`] and step
    each pixel's transmittance and R back past it (state: trans, rest, taken, upstream), on
    the runs of cells `_forward_gaussian` ran, with what it kept (its α on, its feet row):
    straight-line per cell, a cell the pair did not draw adding zeros, keeping its state."""
    features = scratch = scene[3]  # scratch: the dtype to round to
    a_min, a_max, _ = _thresholds(scratch, limits)
    means2d, conics, (alphas, foot) = scene[0], scene[1], kept
    mx, my, a, b, c = means2d[g, 0], means2d[g, 1], conics[g, 0], conics[g, 1], conics[g, 2]
    r0, r1, b0, b1 = foot[1], foot[2], foot[3], foot[4]  # not unpacked: that was 2× slower
    f0, f1, f2, f3 = features[g, 0], features[g, 1], features[g, 2], features[g, 3]
    trans, rest, taken, (u0s, u1s, u2s, u3s, u4s) = state
    xs, ys = centres
    column_cells = (box[3] - box[1]) * LANES
    run = max(r1 + 1 - r0, 0) * LANES
    g_mx = g_my = g_a = g_b = g_c = g_lo = g_r = g_g = g_bl = g_d = abs_x = abs_y = 0.0
    for block in range(b0, b1 + 1):
        first = block * column_cells + r0 * LANES
        here = alphas[(block - b0) * run :]
        for j in range(run):
            p = np.uint64(first + j)
            dx, dy = xs[p] - mx, ys[p] - my
            raw = here[j]
            alpha = min(raw, a_max)
            live = (k <= taken[p]) & (alpha >= a_min)
            shape = live & (not raw > a_max)  # α not clamped: it moves with the shape
            al, keep = float(alpha), float(_to_dtype(scratch, 1.0 - alpha))
            t_before = trans[p] / keep
            w = al * t_before if live else 0.0
            u0, u1, u2, u3 = u0s[p], u1s[p], u2s[p], u3s[p]
            s = u0 * f0 + u1 * f1 + u2 * f2 + u3 * f3 + u4s[p]
            g_r += w * u0 if live else 0.0
            g_g += w * u1 if live else 0.0
            g_bl += w * u2 if live else 0.0
            g_d += w * u3 if live else 0.0
            d_exp = t_before * (s - rest[p]) * al if shape else 0.0
            rest[p] = s * al + keep * rest[p] if live else rest[p]
            trans[p] = t_before if live else trans[p]
            d_mx = d_exp * (a * dx + b * dy) if shape else 0.0
            d_my = d_exp * (b * dx + c * dy) if shape else 0.0
            g_mx += d_mx
            g_my += d_my
            abs_x += abs(d_mx)
            abs_y += abs(d_my)
            g_a -= 0.5 * d_exp * dx * dx if shape else 0.0
            g_b -= d_exp * dx * dy if shape else 0.0
            g_c -= 0.5 * d_exp * dy * dy if shape else 0.0
            g_lo += d_exp
    grad[0], grad[1], grad[2], grad[3], grad[4], grad[5] = g_mx, g_my, g_a, g_b, g_c, g_lo
    grad[6], grad[7], grad[8], grad[9], grad[10], grad[11] = g_r, g_g, g_bl, g_d, abs_x, abs_y


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


RADIX_BITS = 11
"""Bits of the key each pass of `stable_argsort` sorts by (2 048 buckets: six passes cover
a float64, and passes on which every key has the same digit are skipped)."""


@njit(cache=True, nogil=True)
def stable_argsort(values: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """The permutation that sorts float64 `values` ascending, equal values in index order:
    `torch.argsort(values, stable=True)` for values without NaN (−0.0 sorts before +0.0,
    where PyTorch takes them as equal). A least-significant-digit radix sort on the
    values' bits, flipped so that their unsigned order is the numeric one (all bits of a
    negative value, the sign bit of a positive one): O(n) per pass, and stable because
    each pass keeps the order of the one before it."""
    n = values.shape[0]
    bits = values.view(np.uint64)
    sign = np.uint64(1) << np.uint64(63)
    keys = np.empty(n, dtype=np.uint64)
    for i in range(n):
        b = bits[i]
        keys[i] = ~b if b & sign else b | sign
    order = np.arange(n)
    spare_keys, spare_order = np.empty_like(keys), np.empty_like(order)
    buckets = 1 << RADIX_BITS
    mask = np.uint64(buckets - 1)
    count = np.empty(buckets, dtype=np.int64)
    for shift in range(0, 64, RADIX_BITS):
        count[:] = 0
        for i in range(n):
            count[(keys[i] >> np.uint64(shift)) & mask] += 1
        if n == 0 or count[(keys[0] >> np.uint64(shift)) & mask] == n:
            continue  # one digit for all: this pass would move nothing
        total = 0
        for d in range(buckets):
            total, count[d] = total + count[d], total
        for i in range(n):
            d = (keys[i] >> np.uint64(shift)) & mask
            spare_keys[count[d]] = keys[i]
            spare_order[count[d]] = order[i]
            count[d] += 1
        keys, spare_keys = spare_keys, keys
        order, spare_order = spare_order, order
    return order


@njit(cache=True, nogil=True)
def bin_by_depth(
    depths: np.ndarray,
    visible: np.ndarray,
    means2d: np.ndarray,
    extents: np.ndarray,
    layout: tuple,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """`stages.bin_tiles` whole: the visible Gaussians in depth order (`stable_argsort`,
    as `stages.depth_order`), each one's pixel box (`project_kernels.pixel_span`, the
    float64 operations of `stages.pixel_range`) as a box of tiles, and the counting sort
    of `bin_pairs`. layout = (tiles_x, tile_size, width, height)."""
    tiles_x, tile_size, width, height = layout
    tiles = tiles_x * -(-height // tile_size)
    shown = np.flatnonzero(visible)
    order = shown[stable_argsort(depths[shown])]
    # Pixel → tile along either axis by table: a 64-bit division per box edge cost more
    # than the rest of binning (a demo frame: ~90 of 180 µs).
    tile_of = np.arange(max(width, height)) // tile_size
    boxes = np.empty((order.shape[0], 4), dtype=np.int64)
    for v in range(order.shape[0]):
        g = order[v]
        c0, c1 = pixel_span(means2d[g, 0], extents[g, 0], float(width))
        r0, r1 = pixel_span(means2d[g, 1], extents[g, 1], float(height))
        if c0 > c1 or r0 > r1:  # not drawn (visible ones always are): no tiles
            boxes[v, 0], boxes[v, 1], boxes[v, 2], boxes[v, 3] = 0, 0, 0, 0
        else:
            boxes[v, 0], boxes[v, 1] = tile_of[c0], tile_of[c1] + 1
            boxes[v, 2], boxes[v, 3] = tile_of[r0], tile_of[r1] + 1
    return bin_pairs(order, boxes, tiles_x, tiles)


@njit(cache=True, nogil=True)
def bin_pairs(
    order: np.ndarray, boxes: np.ndarray, tiles_x: int, tiles: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """`stages.bin_tiles` as a counting sort: the Gaussians `order` (depth order) with
    half-open boxes of tiles [columns 0:1, rows 2:3] → (Gaussian of each pair, first pair
    of each tile, pairs per tile). One pass counts each tile's pairs, a second deals the
    Gaussians out in depth order, so every tile's list comes out front to back, exactly as
    the stable sort by tile of the reference leaves it."""
    count = np.zeros(tiles, dtype=np.int64)
    for v in range(order.shape[0]):
        for ty in range(boxes[v, 2], boxes[v, 3]):
            for tx in range(boxes[v, 0], boxes[v, 1]):
                count[ty * tiles_x + tx] += 1
    start = np.empty(tiles, dtype=np.int64)
    total = 0
    for t in range(tiles):
        start[t] = total
        total += count[t]
    gaussian = np.empty(total, dtype=np.int64)
    fill = start.copy()
    for v in range(order.shape[0]):
        for ty in range(boxes[v, 2], boxes[v, 3]):
            for tx in range(boxes[v, 0], boxes[v, 1]):
                t = ty * tiles_x + tx
                gaussian[fill[t]] = order[v]
                fill[t] += 1
    return gaussian, start, count

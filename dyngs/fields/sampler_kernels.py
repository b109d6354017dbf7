"""The compiled bilinear plane sampler of `field:hexplane` (numba), forward and backward.

Letters: G planes of one group, C channels, H×W nodes of a plane, N points, B = BLOCK.

It computes what `F.grid_sample(planes − shift, grid, "bilinear", "border",
align_corners=True) + shift` computes (the reference, `plane_sampler.reference_sample`),
for the field's grids: plane g is read at the coordinate columns (a_g, b_g) of every
point, a along W and b along H. PyTorch's CPU kernel vectorises over points and, in its
backward, adds each point's gradient into the plane one channel at a time, H·W values
apart. Here:
- `placements` finds, once per plane and point, the four corner nodes and the two
  fractions (with every job placing each point again, the field ran only 1.1-1.2× faster
  than with grid_sample; placed once, 1.5×), and each plane's span: the rectangle of
  nodes its points read (a time plane's two rows of 134 on hfu-3cam, where a step
  draws one time);
- `planes_channels_last` copies each plane's span (or, where the points read few of its
  nodes, only those), less the shift, once a forward, as [G, H, W, C], so that a node's
  C channels are adjacent; the backward reads the copy;
- `sample_forward` is one job per (plane, run of CHUNK points): each point reads its
  four corners as runs of C values, which LLVM vectorises, and writes its C samples side
  by side, [G, N, C] (the layout the compiled products read);
- `sample_backward` has two kinds of job. One per (plane, block of channels) adds each
  point's upstream gradient into that block's four corners, in a private buffer the
  size of the plane's span (or one row per node read, where they are few), point by
  point in order, and writes zeros at the nodes no point read: the same digits either
  way and at any block size, which only shares the work (`plane_block`). One
  per (plane, run of CHUNK points) forms each point's gradient on its two coordinates,
  a sum over the C channels.
Loops over a block's channels run to a length known only when the kernel runs: numba
leaves LLVM's SLP vectoriser off (numba PR #8852, after miscompilations), and its loop
vectoriser leaves a loop of a constant 8 iterations scalar (the planes' half of the
backward ran 1.4-2.2× slower than with the same 8 read at run time, on the demo's plane
shapes and random points). The coordinates' channel sum is compiled with
`fastmath={"reassoc"}` alone, so that LLVM may add it in vector lanes (3.3× faster than
the fixed lanes and tree it replaced): the order follows the machine's vector width, so
the last bits may differ between machines (as PyTorch's own kernels' do), never between
runs or thread counts on one. No other fast-math assumption is made: NaN and infinity
keep their meaning. Every job writes its own part of every output, in an order that does
not depend on how jobs fall to threads, so the results are the same at every thread
count.

Placement, as grid_sample's: x ↦ (x + 1)/2 · (W − 1), clipped to [0, W − 1]. The
coordinate's gradient is zero where the clip holds it at an edge (or beyond), as
grid_sample's border padding makes it. The field clamps its coordinates to [-1, 1] and
replaces non-finite ones before they get here (`space_time`); a NaN is still placed at
node 0, so that no index can leave the plane.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from dyngs.compiled import noalias_option
from dyngs.fields.plane_sampler import BLOCK

CHUNK = 256
"""Points a forward or coordinate-gradient job takes. Each point's results are its own, so
the split changes only how the work is shared, never a digit."""

_NOALIAS = noalias_option()

WIDE_BLOCK = 16
"""Channels a plane job takes where the channels are a multiple of it and more than it
(`plane_block`)."""


def plane_block(channels: int) -> int:
    """The channels one plane job of `sample_backward` takes: WIDE_BLOCK where that leaves
    at least two jobs a plane, else BLOCK. On inputs captured from a demo step (32
    channels, two threads) the kernel's four calls took 1.08× less time with 16 than
    with 8; on a texture step's (16 channels, one or two planes a group) 8 was 1.07×
    faster. The digits are the same either way."""
    if channels % WIDE_BLOCK == 0 and channels > WIDE_BLOCK:
        return WIDE_BLOCK
    return BLOCK


@njit(cache=True, nogil=True, inline="always")
def _place(x, one, half, last):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """Where grid coordinate x falls on an axis of last + 1 nodes (all in the planes' dtype):
    (the node before it, the node after it (the last node at the end), the fraction of
    the way between them, and 1 where the clip to [0, last] left it free, else 0)."""
    zero = one - one
    raw = (x + one) * half * last
    free = one if (raw > zero and raw < last) else zero
    position = raw
    if not position >= zero:  # before the first node, or NaN
        position = zero
    elif position > last:
        position = last
    node = np.floor(position)
    first = int(node)
    return first, min(first + 1, int(last)), position - node, free


@njit(parallel=True, cache=True, nogil=True)
def placements(coords, columns, one, half, lasts, nodes, fractions, spans, slots):  # type: ignore[no-untyped-def]  # pragma: no cover
    """For each plane g and point n: nodes[g, n] = (x0, x1, y0, y1) and fractions[g, n] =
    (fx, fy, x free, y free), from columns (a_g, b_g) of coords; lasts = (W − 1, H − 1).
    spans[g] = (first x, last x, first y, last y, nodes read): the rectangle of nodes
    any point of plane g reads, (0, −1, 0, −1, 0) when there are no points, and how many
    nodes they read; slots [G, H, W], all zero on entry, numbers the nodes read 1, 2, …
    in the order the points first read them."""
    groups, n = nodes.shape[0], coords.shape[0]
    for g in prange(groups):
        a, b = columns[2 * g], columns[2 * g + 1]
        x_first, x_last = int(lasts[0]), 0
        y_first, y_last = int(lasts[1]), 0
        read = 0
        marks = slots[g]
        for i in range(n):
            x0, x1, fx, x_free = _place(coords[i, a], one, half, lasts[0])
            y0, y1, fy, y_free = _place(coords[i, b], one, half, lasts[1])
            nodes[g, i, 0], nodes[g, i, 1], nodes[g, i, 2], nodes[g, i, 3] = x0, x1, y0, y1
            fractions[g, i, 0], fractions[g, i, 1] = fx, fy
            fractions[g, i, 2], fractions[g, i, 3] = x_free, y_free
            x_first, x_last = min(x_first, x0), max(x_last, x1)
            y_first, y_last = min(y_first, y0), max(y_last, y1)
            read = _mark(marks, y0, x0, read)
            read = _mark(marks, y0, x1, read)
            read = _mark(marks, y1, x0, read)
            read = _mark(marks, y1, x1, read)
        if n == 0:
            x_first, x_last, y_first, y_last = 0, -1, 0, -1
        spans[g, 0], spans[g, 1], spans[g, 2], spans[g, 3] = x_first, x_last, y_first, y_last
        spans[g, 4] = read


@njit(cache=True, nogil=True, inline="always")
def _mark(marks, y, x, read):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """Number node (y, x) read + 1 if no point read it before; the nodes read now."""
    if marks[y, x] == 0:
        read += 1
        marks[y, x] = read
    return read


SPARSE = 4
"""A plane whose points read fewer than 1/SPARSE of its span's nodes is copied node by
node (`planes_channels_last`) and its gradient gathered node by node (`sample_backward`);
the rest row by row."""


@njit(cache=True, nogil=True, inline="always")
def _sparse(span):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """Whether a plane's points read fewer than 1/SPARSE of its span's nodes."""
    return span[4] * SPARSE < (span[1] + 1 - span[0]) * (span[3] + 1 - span[2])


@njit(parallel=True, cache=True, nogil=True)
def planes_channels_last(planes, shift, spans, slots, values):  # type: ignore[no-untyped-def]  # pragma: no cover
    """values[g, h, w, c] = planes[g, c, h, w] − shift at every node the points of plane g
    read (`placements`); values elsewhere are left as they are. One job per (plane, row).
    A row of a plane whose points read few of its span's nodes (under 1/SPARSE) copies
    only the nodes read, a node's C channels H·W values apart; the others copy the span's
    columns of each channel's row, which is contiguous."""
    groups, channels, height = planes.shape[:3]
    for job in prange(groups * height):
        g, h = job // height, job % height
        if h < spans[g, 2] or h > spans[g, 3]:
            continue
        first, last = spans[g, 0], spans[g, 1] + 1
        if _sparse(spans[g]):
            marks = slots[g, h]
            for w in range(first, last):
                if marks[w]:
                    node = values[g, h, w]
                    for c in range(channels):
                        node[c] = planes[g, c, h, w] - shift
            continue
        for c in range(channels):
            row = planes[g, c, h]
            for w in range(first, last):
                values[g, h, w, c] = row[w] - shift


@njit(cache=True, nogil=True, inline="always")
def _weights(fractions, n, one):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """Point n's fractions, their complements and its four corners' bilinear weights:
    (fx, fy, 1 − fx, 1 − fy, nw, ne, sw, se)."""
    fx, fy = fractions[n, 0], fractions[n, 1]
    gx, gy = one - fx, one - fy
    return fx, fy, gx, gy, gx * gy, fx * gy, gx * fy, fx * fy


@njit(parallel=True, cache=True, nogil=True)
def sample_forward(values, nodes, fractions, shift, one, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    """out[g, n, c] = plane g's channel c, bilinearly at point n's place (`placements`);
    values [G, H, W, C] from `planes_channels_last`, out [G, N, C]. `one` carries the planes'
    dtype, so that float32 arithmetic stays float32."""
    groups, n = out.shape[0], out.shape[1]
    chunks = (n + CHUNK - 1) // CHUNK
    for job in prange(groups * chunks):
        g, first = job // chunks, job % chunks * CHUNK
        _forward_chunk(values[g], nodes[g], fractions[g], shift, one, out[g], first,
                       min(first + CHUNK, n))  # fmt: skip


@njit(cache=True, nogil=True, **_NOALIAS)
def _forward_chunk(values, nodes, fractions, shift, one, out, first, last):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Points first … last of one plane."""
    channels = values.shape[2]
    for n in range(first, last):
        x0, x1, y0, y1 = nodes[n, 0], nodes[n, 1], nodes[n, 2], nodes[n, 3]
        _, _, _, _, nw, ne, sw, se = _weights(fractions, n, one)
        for c in range(channels):
            value = values[y0, x0, c] * nw + values[y0, x1, c] * ne
            value += values[y1, x0, c] * sw + values[y1, x1, c] * se
            out[n, c] = value + shift


@njit(parallel=True, cache=True, nogil=True)
def sample_backward(  # type: ignore[no-untyped-def]  # pragma: no cover
    values, nodes, fractions, one, scales, upstream, block, spans, slots, grads, coords
):
    """From upstream [G, N, C], the gradient of `sample_forward`'s out: grads [G, C, H, W]
    for the planes, `block` channels a job (a divisor of C, `plane_block`), zero at every
    node no point read (spans and slots from `placements`), and coords [N, G, 2], each
    plane's gradient on its two coordinate columns at every point (none when coords holds
    no points); scales = ((W − 1)/2, (H − 1)/2), the grid's nodes per unit of coordinate."""
    groups, channels = values.shape[0], values.shape[3]
    blocks = channels // block
    # Two loops, so that each shares its own kind of job evenly among the threads.
    for job in prange(groups * blocks):
        g, c0 = job // blocks, job % blocks * block
        out = grads[g, c0 : c0 + block]
        if _sparse(spans[g]):
            _nodes_job(nodes[g], fractions[g], one, upstream[g], c0, spans[g], slots[g], out)
        else:
            _span_job(nodes[g], fractions[g], one, upstream[g], c0, spans[g], out)
    n = coords.shape[0]
    chunks = (n + CHUNK - 1) // CHUNK
    for job in prange(groups * chunks):
        g, first = job // chunks, job % chunks * CHUNK
        _coordinate_chunk(values[g], nodes[g], fractions[g], one, scales, upstream[g],
                          coords[:, g], first, min(first + CHUNK, n))  # fmt: skip


@njit(cache=True, nogil=True)
def _span_job(nodes, fractions, one, upstream, c0, span, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    """out [block, H, W], one plane's gradient in channels c0 … c0 + block: the points'
    upstream gradients added into a private buffer of the plane's span, then written out,
    zero outside the span."""
    block, height = out.shape[0], out.shape[1]
    x_first, x_last, y_first, y_last = span[0], span[1], span[2], span[3]
    sums = np.zeros((y_last + 1 - y_first, x_last + 1 - x_first, block), out.dtype)
    _plane_job(nodes, fractions, one, upstream, c0, x_first, y_first, sums)
    zero = one - one
    for c in range(block):
        grad = out[c]
        for h in range(height):
            row = grad[h]
            if h < y_first or h > y_last:
                row[:] = zero
                continue
            row[:x_first] = zero
            row[x_last + 1 :] = zero
            kept = sums[h - y_first]
            for w in range(x_first, x_last + 1):
                row[w] = kept[w - x_first, c]


@njit(cache=True, nogil=True, **_NOALIAS)
def _plane_job(nodes, fractions, one, upstream, c0, x_first, y_first, sums):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Add every point's upstream gradient in channels c0 … c0 + block into its four
    corners of sums [span's rows, span's columns, block], whose first node is (y_first,
    x_first), point by point in order."""
    block = sums.shape[2]
    for n in range(nodes.shape[0]):
        x0, x1 = nodes[n, 0] - x_first, nodes[n, 1] - x_first
        y0, y1 = nodes[n, 2] - y_first, nodes[n, 3] - y_first
        _, _, _, _, nw, ne, sw, se = _weights(fractions, n, one)
        up = upstream[n, c0 : c0 + block]
        # One loop a corner: at the last node the corners coincide (x1 = x0), so a
        # single loop adding to all four could not be vectorised.
        _add_scaled(sums[y0, x0], up, nw)
        _add_scaled(sums[y0, x1], up, ne)
        _add_scaled(sums[y1, x0], up, sw)
        _add_scaled(sums[y1, x1], up, se)


@njit(cache=True, nogil=True, **_NOALIAS)
def _nodes_job(nodes, fractions, one, upstream, c0, span, slots, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    """`_span_job` for a plane whose points read few of its span's nodes: the private
    buffer holds one row per node read (slots [H, W], from `placements`), and the gradient
    is gathered from it, zero at the nodes no point read."""
    block, height = out.shape[0], out.shape[1]
    sums = np.zeros((span[4], block), out.dtype)
    for n in range(nodes.shape[0]):
        x0, x1, y0, y1 = nodes[n, 0], nodes[n, 1], nodes[n, 2], nodes[n, 3]
        _, _, _, _, nw, ne, sw, se = _weights(fractions, n, one)
        up = upstream[n, c0 : c0 + block]
        _add_scaled(sums[slots[y0, x0] - 1], up, nw)
        _add_scaled(sums[slots[y0, x1] - 1], up, ne)
        _add_scaled(sums[slots[y1, x0] - 1], up, sw)
        _add_scaled(sums[slots[y1, x1] - 1], up, se)
    zero = one - one
    for c in range(block):
        grad = out[c]
        for h in range(height):
            row = grad[h]
            if h < span[2] or h > span[3]:
                row[:] = zero
                continue
            marks = slots[h]
            for w in range(row.shape[0]):
                slot = marks[w]
                row[w] = sums[slot - 1, c] if slot > 0 else zero


@njit(cache=True, nogil=True, inline="always")
def _add_scaled(into, up, weight):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """into += up · weight, elementwise."""
    for c in range(into.shape[0]):
        into[c] += up[c] * weight


@njit(cache=True, nogil=True, fastmath={"reassoc"}, **_NOALIAS)
def _coordinate_chunk(values, nodes, fractions, one, scales, upstream, coords, first, last):  # type: ignore[no-untyped-def]  # pragma: no cover
    """coords[n] for points first … last of one plane: Σ_c upstream[n, c] times the
    bilinear sample's derivative along each axis, the sum in the order LLVM vectorises
    it (the module's docstring says why)."""
    for n in range(first, last):
        x0, x1, y0, y1 = nodes[n, 0], nodes[n, 1], nodes[n, 2], nodes[n, 3]
        fx, fy, gx, gy, _, _, _, _ = _weights(fractions, n, one)
        v00, v01, v10, v11 = values[y0, x0], values[y0, x1], values[y1, x0], values[y1, x1]
        u = upstream[n]
        along_x = one - one
        along_y = along_x
        for c in range(u.shape[0]):
            along_x += u[c] * ((v01[c] - v00[c]) * gy + (v11[c] - v10[c]) * fy)
            along_y += u[c] * ((v10[c] - v00[c]) * gx + (v11[c] - v01[c]) * fx)
        coords[n, 0] = along_x * scales[0] * fractions[n, 2]
        coords[n, 1] = along_y * scales[1] * fractions[n, 3]

"""The compiled bilinear plane sampler of `field:hexplane` (numba), forward and backward.

Letters: G planes of one group, C channels, H×W nodes of a plane, N points, B = BLOCK.

It computes what `F.grid_sample(planes − shift, grid, "bilinear", "border",
align_corners=True) + shift` computes (the reference, `plane_sampler.reference_sample`),
for the field's grids: plane g is read at the coordinate columns (a_g, b_g) of every
point, a along W and b along H. PyTorch's CPU kernel vectorises over points and, in its
backward, adds each point's gradient into the plane one channel at a time, H·W values
apart. Here `placements` first finds, once per plane and point, the four corner nodes
and the two fractions (with every job placing each point again, the field ran only
1.1-1.2× faster than with grid_sample; placed once, 1.5×). Then a job is one plane and a
block of B channels. It copies its block channels-last, [H, W, B], so that the B
channels of a node are adjacent; then for each point it reads (forward) or adds into
(backward) the four corner nodes as runs of B values, which LLVM vectorises. Its jobs
write disjoint parts of every output, and each walks its points in order, so the results
are the same at every thread count.

Placement, as grid_sample's: x ↦ (x + 1)/2 · (W − 1), clipped to [0, W − 1]. The
coordinate's gradient is zero where the clip holds it at an edge (or beyond), as
grid_sample's border padding makes it. The field clamps its coordinates to [-1, 1] and
replaces non-finite ones before they get here (`space_time`); a NaN is still placed at
node 0, so that no index can leave the plane.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from dyngs.fields.plane_sampler import BLOCK


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
def placements(coords, columns, one, half, lasts, nodes, fractions):  # type: ignore[no-untyped-def]  # pragma: no cover
    """For each plane g and point n: nodes[g, n] = (x0, x1, y0, y1) and fractions[g, n] =
    (fx, fy, x free, y free), from columns (a_g, b_g) of coords; lasts = (W − 1, H − 1)."""
    groups, n = nodes.shape[0], coords.shape[0]
    for g in prange(groups):
        a, b = columns[2 * g], columns[2 * g + 1]
        for i in range(n):
            x0, x1, fx, x_free = _place(coords[i, a], one, half, lasts[0])
            y0, y1, fy, y_free = _place(coords[i, b], one, half, lasts[1])
            nodes[g, i, 0], nodes[g, i, 1], nodes[g, i, 2], nodes[g, i, 3] = x0, x1, y0, y1
            fractions[g, i, 0], fractions[g, i, 1] = fx, fy
            fractions[g, i, 2], fractions[g, i, 3] = x_free, y_free


@njit(cache=True, nogil=True)
def _block(planes, g, c0, shift):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """Channels c0 … c0 + B of plane g, minus shift, as [H, W, B]."""
    _, _, height, width = planes.shape
    block = np.empty((height, width, BLOCK), planes.dtype)
    for c in range(BLOCK):
        plane = planes[g, c0 + c]
        for h in range(height):
            for w in range(width):
                block[h, w, c] = plane[h, w] - shift
    return block


@njit(cache=True, nogil=True, inline="always")
def _weights(fractions, g, n, one):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """Point n's fractions on plane g, their complements and its four corners' bilinear
    weights: (fx, fy, 1 − fx, 1 − fy, nw, ne, sw, se)."""
    fx, fy = fractions[g, n, 0], fractions[g, n, 1]
    gx, gy = one - fx, one - fy
    return fx, fy, gx, gy, gx * gy, fx * gy, gx * fy, fx * fy


@njit(parallel=True, cache=True, nogil=True)
def sample_forward(planes, nodes, fractions, shift, one, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    """out[g, c, n] = plane g's channel c, bilinearly at point n's place (`placements`);
    planes [G, C, H, W], out [G, C, N]. `one` carries the planes' dtype, so that float32
    arithmetic stays float32."""
    groups, channels = planes.shape[:2]
    blocks = channels // BLOCK
    for job in prange(groups * blocks):
        g, c0 = job // blocks, job % blocks * BLOCK
        block = _block(planes, g, c0, shift)
        for n in range(nodes.shape[1]):
            x0, x1, y0, y1 = nodes[g, n, 0], nodes[g, n, 1], nodes[g, n, 2], nodes[g, n, 3]
            _, _, _, _, nw, ne, sw, se = _weights(fractions, g, n, one)
            for c in range(BLOCK):
                value = block[y0, x0, c] * nw + block[y0, x1, c] * ne
                value += block[y1, x0, c] * sw + block[y1, x1, c] * se
                out[g, c0 + c, n] = value + shift


@njit(parallel=True, cache=True, nogil=True)
def sample_backward(planes, nodes, fractions, shift, one, scales, upstream, grads, partial):  # type: ignore[no-untyped-def]  # pragma: no cover
    """From upstream [G, C, N], the gradient of `sample_forward`'s out: grads [G, C, H, W]
    for the planes, and partial [G, C / B, N, 2], each job's share of the gradient on
    point n's two columns (summed over the blocks by the caller, in order); scales =
    ((W − 1)/2, (H − 1)/2), the grid's nodes per unit of coordinate."""
    groups, channels, height, width = planes.shape
    blocks = channels // BLOCK
    for job in prange(groups * blocks):
        g, k = job // blocks, job % blocks
        c0 = k * BLOCK
        block = _block(planes, g, c0, shift)
        sums = np.zeros((height, width, BLOCK), planes.dtype)
        up = np.empty(BLOCK, planes.dtype)
        for n in range(nodes.shape[1]):
            x0, x1, y0, y1 = nodes[g, n, 0], nodes[g, n, 1], nodes[g, n, 2], nodes[g, n, 3]
            fx, fy, gx, gy, nw, ne, sw, se = _weights(fractions, g, n, one)
            for c in range(BLOCK):
                up[c] = upstream[g, c0 + c, n]
            # One loop a corner: at the last node the corners coincide (x1 = x0), so a
            # single loop adding to all four could not be vectorised.
            for c in range(BLOCK):
                sums[y0, x0, c] += up[c] * nw
            for c in range(BLOCK):
                sums[y0, x1, c] += up[c] * ne
            for c in range(BLOCK):
                sums[y1, x0, c] += up[c] * sw
            for c in range(BLOCK):
                sums[y1, x1, c] += up[c] * se
            dx = dy = one - one
            for c in range(BLOCK):
                v00, v01 = block[y0, x0, c], block[y0, x1, c]
                v10, v11 = block[y1, x0, c], block[y1, x1, c]
                dx += up[c] * ((v01 - v00) * gy + (v11 - v10) * fy)
                dy += up[c] * ((v10 - v00) * gx + (v11 - v01) * fx)
            partial[g, k, n, 0] = dx * scales[0] * fractions[g, n, 2]
            partial[g, k, n, 1] = dy * scales[1] * fractions[g, n, 3]
        for c in range(BLOCK):
            grad = grads[g, c0 + c]
            for h in range(height):
                for w in range(width):
                    grad[h, w] = sums[h, w, c]

"""The compiled per-scale plane product of `field:hexplane` (numba), forward and backward.

Letters: N points, F feature channels, S scales.

`HexPlaneField.forward` multiplies each scale's six sampled planes in a fixed order,
((((p0 · p1) · p2) · p3) · p4) · p5, and sets the scales' products side by side. As
PyTorch operations (`hexplane.plane_products`, the reference) that is five
multiplications a scale forward, ten backward, and the copies that stack and concatenate
them, each a pass over an [F, N] array; here each direction is one pass (docs/TRAINING.md
has the timings). The samples come channels last, [N, F] a plane, as the compiled
sampler writes them, so the output [N, S·F] is written in place, a point's channels
side by side, and the backward reads its upstream gradient so and writes the planes'
gradients so, for the sampler's backward to read. Every product is formed in the same
order and dtype as PyTorch forms it, and the backward is autograd's chain written out
(each multiplication's gradient is the upstream one times the other factor), so values
and gradients are the same to the bit (tests/fields/test_plane_product.py).
"""

from __future__ import annotations

from numba import njit, prange

from dyngs.compiled import noalias_option

CHUNK = 256
"""Points a job takes. Every value is a point's own, so the split changes no digit."""

_NOALIAS = noalias_option()

# The planes come as one flat tuple, six a scale: numba hands a tuple of arrays to the
# threads of a parallel loop, but not a tuple of such tuples.


@njit(parallel=True, cache=True, nogil=True)
def product_forward(parts: tuple, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    """out[n, s·F + f] = the product of scale s's six planes at (n, f); parts holds each
    scale's six [N, F] samples in turn, in the field's order. One job per run of CHUNK
    points."""
    n = out.shape[0]
    for job in prange((n + CHUNK - 1) // CHUNK):
        first = job * CHUNK
        _forward_chunk(parts, out, first, min(first + CHUNK, n))


@njit(cache=True, nogil=True)
def _forward_chunk(parts: tuple, out, first: int, last: int):  # type: ignore[no-untyped-def]  # pragma: no cover
    channels = parts[0].shape[1]
    for s in range(len(parts) // 6):
        p0, p1, p2, p3, p4, p5 = _six(parts, 6 * s)
        for i in range(first, last):
            row = out[i, s * channels : (s + 1) * channels]
            for f in range(channels):
                row[f] = p0[i, f] * p1[i, f] * p2[i, f] * p3[i, f] * p4[i, f] * p5[i, f]


@njit(parallel=True, cache=True, nogil=True)
def product_backward(parts: tuple, upstream, grads: tuple):  # type: ignore[no-untyped-def]  # pragma: no cover
    """grads (laid out as parts) from upstream [N, S·F], the gradient of
    `product_forward`'s output. Back through r_k = r_(k−1) · p_k from r_5 to
    r_1 = p0 · p1, as autograd does: ∂/∂p_k = g · r_(k−1), then g ← g · p_k."""
    n = upstream.shape[0]
    for job in prange((n + CHUNK - 1) // CHUNK):
        first = job * CHUNK
        _backward_chunk(parts, upstream, grads, first, min(first + CHUNK, n))


@njit(cache=True, nogil=True)
def _backward_chunk(parts: tuple, upstream, grads: tuple, first: int, last: int):  # type: ignore[no-untyped-def]  # pragma: no cover
    channels = parts[0].shape[1]
    for s in range(len(parts) // 6):
        p0, p1, p2, p3, p4, p5 = _six(parts, 6 * s)
        g0, g1, g2, g3, g4, g5 = _six(grads, 6 * s)
        row = upstream[:, s * channels : (s + 1) * channels]
        _backward_rows(p0, p1, p2, p3, p4, p5, row, g0, g1, g2, g3, g4, g5, first, last)


@njit(cache=True, nogil=True, **_NOALIAS)
def _backward_rows(p0, p1, p2, p3, p4, p5, upstream, g0, g1, g2, g3, g4, g5, first, last):  # type: ignore[no-untyped-def]  # pragma: no cover
    """One scale's rows first … last. Its own function, with the arrays as arguments, so
    that they can be marked as never overlapping: taken from tuples, LLVM had to assume
    that each of the six stores might change the planes it reads next, and the loop ran
    2-4× slower on the demo's shapes (docs/TRAINING.md)."""
    for i in range(first, last):
        for f in range(p0.shape[1]):
            r1 = p0[i, f] * p1[i, f]
            r2 = r1 * p2[i, f]
            r3 = r2 * p3[i, f]
            r4 = r3 * p4[i, f]
            g = upstream[i, f]
            g5[i, f] = g * r4
            g = g * p5[i, f]
            g4[i, f] = g * r3
            g = g * p4[i, f]
            g3[i, f] = g * r2
            g = g * p3[i, f]
            g2[i, f] = g * r1
            g = g * p2[i, f]
            g1[i, f] = g * p0[i, f]
            g0[i, f] = g * p1[i, f]


@njit(cache=True, nogil=True, inline="always")
def _six(arrays: tuple, first: int) -> tuple:  # pragma: no cover - compiled
    """arrays[first : first + 6]."""
    return (arrays[first], arrays[first + 1], arrays[first + 2], arrays[first + 3],
            arrays[first + 4], arrays[first + 5])  # fmt: skip

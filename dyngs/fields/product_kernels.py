"""The compiled per-scale plane product of `field:hexplane` (numba), forward and backward.

Letters: N points, F feature channels, S scales.

`HexPlaneField.forward` multiplies each scale's six sampled planes in a fixed order,
((((p0 · p1) · p2) · p3) · p4) · p5, and sets the scales' products side by side. As
PyTorch operations (`hexplane.plane_products`, the reference) that is five
multiplications a scale forward, ten backward, and the copies that stack and concatenate
them, each a pass over an [F, N] array; here each direction is one pass
(docs/TRAINING.md has the timings). Every product is formed in the same order and dtype
as PyTorch forms it, and the backward is autograd's chain written out (each
multiplication's gradient is the upstream one times the other factor), so values and
gradients are the same to the bit (tests/fields/test_plane_product.py).
"""

from __future__ import annotations

from numba import njit, prange

# The planes come as one flat tuple, six a scale: numba hands a tuple of arrays to the
# threads of a parallel loop, but not a tuple of such tuples. Each loop calls a function
# per job, which takes its scale's six out of it.


@njit(parallel=True, cache=True, nogil=True)
def product_forward(parts: tuple, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    """out[s·F + f, n] = the product of scale s's six planes at (f, n); parts holds each
    scale's six [F, N] samples in turn, in the field's order. One job per (scale,
    channel)."""
    for job in prange(len(parts) // 6 * parts[0].shape[0]):
        _forward_job(parts, job, out)


@njit(cache=True, nogil=True)
def _forward_job(parts: tuple, job: int, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    channels, n = parts[0].shape
    f, first = job % channels, job // channels * 6
    p0, p1, p2, p3, p4, p5 = _six(parts, first)
    row = out[job]
    for i in range(n):
        row[i] = p0[f, i] * p1[f, i] * p2[f, i] * p3[f, i] * p4[f, i] * p5[f, i]


@njit(parallel=True, cache=True, nogil=True)
def product_backward(parts: tuple, upstream, grads: tuple):  # type: ignore[no-untyped-def]  # pragma: no cover
    """grads (laid out as parts) from upstream [S·F, N], the gradient of `product_forward`'s
    output. Back through r_k = r_(k−1) · p_k from r_5 to r_1 = p0 · p1, as autograd does:
    ∂/∂p_k = g · r_(k−1), then g ← g · p_k."""
    for job in prange(len(parts) // 6 * parts[0].shape[0]):
        _backward_job(parts, upstream, grads, job)


@njit(cache=True, nogil=True)
def _backward_job(parts: tuple, upstream, grads: tuple, job: int):  # type: ignore[no-untyped-def]  # pragma: no cover
    channels, n = parts[0].shape
    f, first = job % channels, job // channels * 6
    p0, p1, p2, p3, p4, p5 = _six(parts, first)
    g0, g1, g2, g3, g4, g5 = _six(grads, first)
    row = upstream[job]
    for i in range(n):
        r1 = p0[f, i] * p1[f, i]
        r2 = r1 * p2[f, i]
        r3 = r2 * p3[f, i]
        r4 = r3 * p4[f, i]
        g = row[i]
        g5[f, i] = g * r4
        g = g * p5[f, i]
        g4[f, i] = g * r3
        g = g * p4[f, i]
        g3[f, i] = g * r2
        g = g * p3[f, i]
        g2[f, i] = g * r1
        g = g * p2[f, i]
        g1[f, i] = g * p0[f, i]
        g0[f, i] = g * p1[f, i]


@njit(cache=True, nogil=True, inline="always")
def _six(arrays: tuple, first: int) -> tuple:  # pragma: no cover - compiled
    """arrays[first : first + 6]."""
    return (arrays[first], arrays[first + 1], arrays[first + 2], arrays[first + 3],
            arrays[first + 4], arrays[first + 5])  # fmt: skip

"""Exact k nearest neighbours of 3D points, without an all-pairs distance matrix.

Letters: N points, C queries in an octree leaf, W points in its window.

Used to size the initial Gaussians (mean distance to their nearest neighbours, Kerbl et
al. 2023) and by the local-rigidity loss (neighbourhoods kept between two times).
"""

from __future__ import annotations

import itertools

import torch
from jaxtyping import Float, Int
from torch import Tensor

KNN_LEAF_SIZE = 256
"""Most queries `knn` handles at once: the leaf size of its octree over the points."""

_MORTON_BITS = 21
"""Octree depth: 2^21 cells per axis, 63 bits of Morton code in all."""


def knn(points: Float[Tensor, "N 3"], k: int) -> Int[Tensor, "N k"]:
    """Exact k nearest neighbours of every point among the others (self excluded).

    Returns [N, min(k, N − 1)] indices, nearest first: a set of N ≤ k points gives every
    other point (N − 1 columns, none for a single point), never padding. Coincident
    points are each other's neighbours at distance 0; self is excluded by index. Among
    equally distant neighbours the choice is arbitrary.

    The search is exact but not all-pairs. Points are sorted along a Morton (Z-order)
    curve and cut into octree cells of at most KNN_LEAF_SIZE points, so a leaf is a
    compact patch of space. For each query, the k-th nearest of a few points next to it
    in Morton order bounds its true k-th distance from above; every true neighbour of a
    leaf therefore lies in the union of the queries' bounding cubes of that radius, and
    only the points in that box are compared, with exact pairwise distances (no matmul
    expansion, whose rounding can misorder near ties). Memory is leaf × candidates
    (at most KNN_LEAF_SIZE × N distances); on spread-out points each query meets a few
    hundred candidates instead of N.
    """
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"points must be [N, 3], got {tuple(points.shape)}")
    if k < 0:
        raise ValueError(f"k must be non-negative, got {k}")
    n = points.shape[0]
    k = min(k, max(n - 1, 0))
    out = torch.empty((n, k), dtype=torch.long, device=points.device)
    if k == 0:
        return out
    if not bool(torch.isfinite(points).all()):
        raise ValueError("knn needs finite points")
    with torch.no_grad():
        # Half precision is searched in float32: its rounding would swamp the distances.
        work = points.detach().to(torch.promote_types(points.dtype, torch.float32))
        codes = _morton_codes(work)
        order = codes.argsort()
        for lo, hi in _octree_leaves(codes[order].cpu(), KNN_LEAF_SIZE):
            # k neighbours of each side in Morton order: the window always holds ≥ k + 1
            # points (n ≥ k + 1), so each query has k others to bound its radius with.
            window = order[max(0, lo - k) : min(n, hi + k)]
            rows = order[lo:hi]
            out[rows] = _knn_leaf(work, rows, window, k)
    return out


def _morton_codes(points: Float[Tensor, "N 3"]) -> Int[Tensor, " N"]:
    """Z-order (Morton) codes of the points on a 2^21 grid over their bounding cube."""
    low = points.min(dim=0).values
    extent = (points.max(dim=0).values - low).max().clamp_min(torch.finfo(points.dtype).tiny)
    cells = (1 << _MORTON_BITS) - 1
    grid = ((points - low) / extent * cells).round().long().clamp(0, cells)
    code = torch.zeros(len(points), dtype=torch.long, device=points.device)
    for bit in range(_MORTON_BITS):  # interleave the bits: ... z1 y1 x1 z0 y0 x0
        for axis in range(3):
            code |= ((grid[:, axis] >> bit) & 1) << (3 * bit + axis)
    return code


def _octree_leaves(codes: Int[Tensor, " N"], size: int) -> list[tuple[int, int]]:
    """Cut sorted Morton codes into ranges of ≤ `size` points, each inside one octree cell
    or a run of sibling cells (so its bounding box stays within their parent)."""
    leaves: list[tuple[int, int]] = []
    stack = [(0, len(codes), 0)]  # (start, stop, octree level of the cell)
    while stack:
        lo, hi, level = stack.pop()
        if hi - lo <= size:
            leaves.append((lo, hi))
            continue
        if level == _MORTON_BITS:  # one finest cell (coincident points): cut it evenly
            leaves.extend((s, min(hi, s + size)) for s in range(lo, hi, size))
            continue
        shift = 3 * (_MORTON_BITS - 1 - level)
        parent = (int(codes[lo]) >> (shift + 3)) << (shift + 3)
        starts = torch.tensor([parent | (child << shift) for child in range(1, 8)])
        edges = [lo, *(lo + torch.searchsorted(codes[lo:hi], starts)).tolist(), hi]
        run = lo  # start of the current run of small siblings
        for a, b in itertools.pairwise(edges):
            if b - a > size:  # a big child: close the run, then split the child
                if a > run:
                    leaves.append((run, a))
                stack.append((a, b, level + 1))
                run = b
            elif b - run > size:  # the run would overflow: close it, start anew at a
                leaves.append((run, a))
                run = a
        if hi > run:
            leaves.append((run, hi))
    return leaves


def _knn_leaf(
    points: Float[Tensor, "N 3"], rows: Int[Tensor, " C"], window: Int[Tensor, " W"], k: int
) -> Int[Tensor, "C k"]:
    """The k nearest neighbours (self excluded) of the points `rows`, exactly; `window`
    holds ≥ k points other than each query, used only to bound the search radius."""
    query = points[rows]
    near = torch.cdist(query, points[window], compute_mode="donot_use_mm_for_euclid_dist")
    near[window[None, :] == rows[:, None]] = float("inf")
    # Widened a little so rounding never drops a point at exactly the radius.
    radius = near.kthvalue(k, dim=1).values[:, None] * (1.0 + 1e-5) + 1e-30
    low = (query - radius).min(dim=0).values
    high = (query + radius).max(dim=0).values
    candidates = ((points >= low) & (points <= high)).all(dim=1).nonzero().squeeze(1)
    d = torch.cdist(query, points[candidates], compute_mode="donot_use_mm_for_euclid_dist")
    d[candidates[None, :] == rows[:, None]] = float("inf")
    return candidates[d.topk(k, dim=1, largest=False, sorted=True).indices]

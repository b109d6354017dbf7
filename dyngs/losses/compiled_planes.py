"""The default plane regularizers in one compiled pass each way, on the CPU.

`plane_values(spatial, temporal)` is (`tv.plane_tv`, `temporal.time_smoothness`,
`temporal.time_l1_to_static`) of the planes held in the stacked groups `spatial` and
`temporal` ([G, F, R1, R0] each, `PlaneGrids.spatial_groups`), as one differentiable [3]
tensor, summed in float64 by `plane_kernels`. Taking the groups, not views of their
planes, each group gets one gradient, written whole: autograd would give every plane
view a zero-filled group-sized gradient of its own and add them up. The PyTorch functions
stay the reference, used off the CPU, without numba and for fields that give no groups;
tests/losses/test_compiled_planes.py holds the two together.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from dyngs.compiled import numba_available, run_kernel, thread_count


def usable(groups: list[Tensor]) -> bool:
    """Whether these stacked plane groups can go through the compiled path: on the CPU
    with numba, contiguous, of one dtype and one channel count."""
    if not groups or not numba_available():
        return False
    first = groups[0]
    return all(
        g.device.type == "cpu" and g.dim() == 4 and g.is_contiguous()
        and g.dtype == first.dtype and g.shape[1] == first.shape[1]
        for g in groups
    )  # fmt: skip


def plane_values(
    spatial: list[Tensor],
    temporal: list[Tensor],
    spatial_whole: list[tuple[int, int]] | None = None,
    temporal_whole: list[tuple[int, int]] | None = None,
) -> Tensor:
    """[plane TV of the planes in `spatial`, time smoothness and time L1 of those in
    `temporal`], each 0 (with no gradient) for an empty list, as the reference functions
    define them: means over planes of each plane's mean, its terms counted on its size in
    `*_whole` (the planes of the groups in order, their sizes before a crop) where given."""
    counts = (_counts(spatial, False, spatial_whole), _counts(temporal, True, temporal_whole))
    return _PlaneValues.apply(len(spatial), counts, *spatial, *temporal)


def _planes(groups: tuple[Tensor, ...]) -> tuple[np.ndarray, ...]:
    """Every plane of the groups, group by group, as [F, R1, R0] arrays (views)."""
    return tuple(plane for g in groups for plane in g.detach().numpy())


def _counts(
    groups: list[Tensor], temporal: bool, whole: list[tuple[int, int]] | None
) -> np.ndarray:
    """[planes, 2]: the terms in each plane's two sums, 0 where the plane is too short for
    them, counted on its [R1, R0] in `whole` where given, else on its own. Spatial: the
    steps along R1 and along R0, F·(R1 − 1)·R0 and F·R1·(R0 − 1). Temporal: the second
    differences in time, F·(T − 2)·R, and every cell, F·T·R."""
    sizes = [(g.shape[1], *g.shape[2:]) for g in groups for _ in range(len(g))]
    if whole:
        sizes = [(f, r1, r0) for (f, _, _), (r1, r0) in zip(sizes, whole, strict=True)]
    rows = []
    for f, r1, r0 in sizes:
        if temporal:
            rows.append((f * max(r1 - 2, 0) * r0, f * r1 * r0))
        else:
            rows.append((f * max(r1 - 1, 0) * r0, f * r1 * max(r0 - 1, 0)))
    return np.array(rows, dtype=np.float64).reshape(-1, 2)


def _per_plane(kernel: Any, planes: tuple[np.ndarray, ...], dtype: str) -> np.ndarray:
    """A sums kernel's two sums for each plane, [planes, 2], added channel by channel."""
    channels = planes[0].shape[0]
    sums = np.empty((len(planes) * channels, 2))
    run_kernel(kernel, thread_count(None), dtype, planes, sums)
    return sums.reshape(len(planes), channels, 2).sum(axis=1)


def _means(sums: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """sums ÷ counts, 0 where a count is 0."""
    return np.divide(sums, counts, out=np.zeros_like(sums), where=counts > 0)


class _PlaneValues(torch.autograd.Function):
    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, spatial_count: int, counts: tuple[np.ndarray, np.ndarray], *groups: Tensor
    ) -> Tensor:
        from dyngs.losses import plane_kernels

        spatial, temporal = groups[:spatial_count], groups[spatial_count:]
        dtype = str(groups[0].dtype)
        values = [0.0, 0.0, 0.0]
        ctx.counts = counts
        if spatial:
            sums = _per_plane(plane_kernels.spatial_sums, _planes(spatial), dtype)
            values[0] = float(_means(sums, ctx.counts[0]).sum(axis=1).mean())
        if temporal:
            sums = _per_plane(plane_kernels.temporal_sums, _planes(temporal), dtype)
            values[1], values[2] = _means(sums, ctx.counts[1]).mean(axis=0).tolist()
        ctx.spatial_count = spatial_count
        ctx.save_for_backward(*groups)
        return torch.tensor(values, dtype=groups[0].dtype)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        from dyngs.losses import plane_kernels

        groups = ctx.saved_tensors
        spatial, temporal = groups[: ctx.spatial_count], groups[ctx.spatial_count :]
        g_tv, g_curve, g_pull = grad.double().tolist()
        grads = tuple(torch.empty_like(g) for g in groups)
        dtype = str(grad.dtype)
        # A plane's sum enters its term as sum ÷ count, and the term is the mean over
        # planes: the weight on a sum is the upstream gradient ÷ (planes × count).
        if spatial:
            planes = _planes(spatial)
            upstream = np.full((len(planes), 2), g_tv / len(planes))
            weights = _means(upstream, ctx.counts[0])
            run_kernel(plane_kernels.spatial_grads, thread_count(None), dtype, planes, weights,
                       _planes(grads[: len(spatial)]))  # fmt: skip
        if temporal:
            planes = _planes(temporal)
            upstream = np.tile([g_curve, g_pull], (len(planes), 1)) / len(planes)
            run_kernel(plane_kernels.temporal_grads, thread_count(None), dtype, planes,
                       _means(upstream, ctx.counts[1]), _planes(grads[len(spatial) :]))  # fmt: skip
        return (None, None, *grads)

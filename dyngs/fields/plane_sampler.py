"""Bilinear sampling of one group of HexPlane planes: compiled on the CPU, `grid_sample`
elsewhere.

`sample_group(planes, coords, columns, shift)` is `reference_sample`'s
`F.grid_sample(planes − shift, grid, "bilinear", "border", align_corners=True) + shift`,
with plane g of the group read at columns (a_g, b_g) of `coords`. On the CPU with numba,
and for channel counts that are a multiple of `BLOCK`, it runs
`sampler_kernels`, which reads and adds a node's channels as one run. The field's
forward and backward then take 0.5-0.65 of their time with `grid_sample` on the demo's
grid (docs/TRAINING.md). The reference stays the definition, and it is used everywhere
else; tests/fields/test_plane_sampler.py holds the two together. The results agree to
rounding, not to the bit: the two sum a sample's four corners, and a point's coordinate
gradient over the channels, in different orders.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from jaxtyping import Float, Int
from torch import Tensor

from dyngs.compiled import numba_available, run_kernel, thread_count

BLOCK = 8
"""Channels a compiled job takes (`sampler_kernels`): eight float32 values, one 256-bit
vector. Defined here so that deciding the path needs no numba import."""


def reference_sample(
    planes: Float[Tensor, "G C H W"],
    coords: Float[Tensor, "N D"],
    columns: Int[Tensor, " 2G"],
    shift: float,
) -> Float[Tensor, "G C 1 N"]:
    """grid_sample(planes − shift) + shift at columns (a_g, b_g) of `coords` for plane g."""
    n, g = coords.shape[0], planes.shape[0]
    # [N, 2G] -> [G, 1, N, 2]: plane i of the group reads columns (a_i, b_i).
    grid = coords.index_select(1, columns).view(n, g, 2).transpose(0, 1).unsqueeze(1)
    if shift == 0.0:
        return F.grid_sample(planes, grid, "bilinear", "border", align_corners=True)
    return F.grid_sample(planes - shift, grid, "bilinear", "border", align_corners=True).add_(shift)


def compiled_usable(planes: Tensor, coords: Tensor) -> bool:
    """Whether `sample_group` takes the compiled path for these tensors."""
    return (
        planes.device.type == "cpu"
        and coords.device.type == "cpu"
        and planes.dtype in (torch.float32, torch.float64)
        and coords.dtype == planes.dtype
        and planes.shape[1] % BLOCK == 0
        and planes.is_contiguous()
        and numba_available()
    )


def sample_group(
    planes: Float[Tensor, "G C H W"],
    coords: Float[Tensor, "N D"],
    columns: Int[Tensor, " 2G"],
    shift: float,
) -> Float[Tensor, "G C 1 N"]:
    """`reference_sample`, compiled where `compiled_usable` says so."""
    if compiled_usable(planes, coords):
        return _SampleGroup.apply(planes, coords, columns, shift)
    return reference_sample(planes, coords, columns, shift)


def _placed(planes: Tensor, coords: Tensor, columns: Tensor) -> tuple[Tensor, Tensor]:
    """Each plane's corner nodes and fractions for every point (`sampler_kernels.placements`)."""
    from dyngs.fields import sampler_kernels

    groups, _, height, width = planes.shape
    kind = _kind(planes.dtype)
    nodes = torch.empty(groups, coords.shape[0], 4, dtype=torch.int64)
    fractions = torch.empty(groups, coords.shape[0], 4, dtype=planes.dtype)
    lasts = np.array([width - 1, height - 1], dtype=kind)
    run_kernel(sampler_kernels.placements, thread_count(None), str(planes.dtype),
               coords.numpy(), columns.numpy(), kind(1.0), kind(0.5), lasts, nodes.numpy(),
               fractions.numpy())  # fmt: skip
    return nodes, fractions


def _kind(dtype: torch.dtype) -> Any:
    """The NumPy scalar type of a float dtype."""
    return np.float32 if dtype == torch.float32 else np.float64


class _SampleGroup(torch.autograd.Function):
    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, planes: Tensor, coords: Tensor, columns: Tensor, shift: float
    ) -> Tensor:
        from dyngs.fields import sampler_kernels

        coords = coords.detach().contiguous()
        columns = columns.detach().contiguous()
        nodes, fractions = _placed(planes, coords, columns)
        groups, channels = planes.shape[:2]
        out = torch.empty(groups, channels, coords.shape[0], dtype=planes.dtype)
        kind = _kind(planes.dtype)
        run_kernel(sampler_kernels.sample_forward, thread_count(None), str(planes.dtype),
                   planes.detach().numpy(), nodes.numpy(), fractions.numpy(), kind(shift),
                   kind(1.0), out.numpy())  # fmt: skip
        ctx.save_for_backward(planes, columns, nodes, fractions)
        ctx.shift, ctx.coords_width = shift, coords.shape[1]
        return out.unsqueeze(2)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        from dyngs.fields import sampler_kernels

        planes, columns, nodes, fractions = ctx.saved_tensors
        groups, channels, height, width = planes.shape
        n = nodes.shape[1]
        upstream = grad.contiguous().view(groups, channels, n)
        grads = torch.empty_like(planes)
        partial = torch.empty(groups, channels // BLOCK, n, 2, dtype=planes.dtype)
        kind = _kind(planes.dtype)
        scales = np.array([(width - 1) / 2, (height - 1) / 2], dtype=kind)
        run_kernel(sampler_kernels.sample_backward, thread_count(None), str(planes.dtype),
                   planes.detach().numpy(), nodes.numpy(), fractions.numpy(), kind(ctx.shift),
                   kind(1.0), scales, upstream.numpy(), grads.numpy(), partial.numpy())  # fmt: skip
        coords_grad = None
        if ctx.needs_input_grad[1]:
            # The blocks' shares in order, then each plane's two columns in the order the
            # reference's index_select backward adds them.
            per_column = partial.sum(dim=1).transpose(0, 1).reshape(n, 2 * groups)
            coords_grad = torch.zeros(n, ctx.coords_width, dtype=planes.dtype)
            coords_grad.index_add_(1, columns, per_column)
        return (grads if ctx.needs_input_grad[0] else None), coords_grad, None, None

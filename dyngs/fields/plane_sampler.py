"""Bilinear sampling of one group of HexPlane planes: compiled on the CPU, `grid_sample`
elsewhere.

`sample_group(planes, coords, columns, shift)` is `reference_sample`'s
`F.grid_sample(planes − shift, grid, "bilinear", "border", align_corners=True) + shift`,
with plane g of the group read at columns (a_g, b_g) of `coords`. On the CPU with numba,
and for channel counts that are a multiple of `BLOCK`, it runs `sampler_kernels`, which
reads and adds a node's channels as one run. Its samples are laid out channels last, a
[G, C, 1, N] view of [G, N, C] (`channels_first`), which the compiled plane products
read, and whose gradient they write, without a transposing copy; docs/TRAINING.md has
the timings. The reference stays the definition, and it is used everywhere else;
tests/fields/test_plane_sampler.py holds the two together. The results agree to
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
"""The compiled path's unit of channels: the channel count must be a multiple of it, and a
plane job of the backward takes this many or twice as many (`sampler_kernels.plane_block`).
Defined here so that deciding the path needs no numba import."""


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


def _placed(
    planes: Tensor, coords: Tensor, columns: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Each plane's corner nodes and fractions for every point, the span of nodes the
    points read on each plane and how many, and the nodes read, numbered from 1
    (`sampler_kernels.placements`)."""
    from dyngs.fields import sampler_kernels

    groups, _, height, width = planes.shape
    kind = _kind(planes.dtype)
    nodes = torch.empty(groups, coords.shape[0], 4, dtype=torch.int64)
    fractions = torch.empty(groups, coords.shape[0], 4, dtype=planes.dtype)
    spans = torch.empty(groups, 5, dtype=torch.int64)
    slots = torch.zeros(groups, height, width, dtype=torch.int32)
    lasts = np.array([width - 1, height - 1], dtype=kind)
    run_kernel(sampler_kernels.placements, thread_count(None), str(planes.dtype),
               coords.numpy(), columns.numpy(), kind(1.0), kind(0.5), lasts, nodes.numpy(),
               fractions.numpy(), spans.numpy(), slots.numpy())  # fmt: skip
    return nodes, fractions, spans, slots


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
        nodes, fractions, spans, slots = _placed(planes, coords, columns)
        groups, channels, height, width = planes.shape
        kind, threads, signature = _kind(planes.dtype), thread_count(None), str(planes.dtype)
        # The planes less the shift, channels last, at the nodes the points read (the rest
        # is never read): read by the forward and the backward.
        values = torch.empty(groups, height, width, channels, dtype=planes.dtype)
        run_kernel(sampler_kernels.planes_channels_last, threads, signature,
                   planes.detach().numpy(), kind(shift), spans.numpy(), slots.numpy(),
                   values.numpy())  # fmt: skip
        out = torch.empty(groups, coords.shape[0], channels, dtype=planes.dtype)
        run_kernel(sampler_kernels.sample_forward, threads, signature, values.numpy(),
                   nodes.numpy(), fractions.numpy(), kind(shift), kind(1.0),
                   out.numpy())  # fmt: skip
        ctx.save_for_backward(values, columns, nodes, fractions, spans, slots)
        ctx.coords_width = coords.shape[1]
        return channels_first(out)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        from dyngs.fields import sampler_kernels

        values, columns, nodes, fractions, spans, slots = ctx.saved_tensors
        groups, height, width, channels = values.shape
        n = nodes.shape[1]
        upstream = channels_last(grad)
        grads = torch.empty(groups, channels, height, width, dtype=values.dtype)
        # No coordinates' gradient wanted: no points for the coordinates' jobs.
        per_plane = torch.empty(n if ctx.needs_input_grad[1] else 0, groups, 2, dtype=values.dtype)
        kind = _kind(values.dtype)
        scales = np.array([(width - 1) / 2, (height - 1) / 2], dtype=kind)
        run_kernel(sampler_kernels.sample_backward, thread_count(None), str(values.dtype),
                   values.numpy(), nodes.numpy(), fractions.numpy(), kind(1.0), scales,
                   upstream.numpy(), sampler_kernels.plane_block(channels), spans.numpy(),
                   slots.numpy(), grads.numpy(), per_plane.numpy())  # fmt: skip
        coords_grad = None
        if ctx.needs_input_grad[1]:
            # Each plane's two columns, in the order the reference's index_select backward
            # adds them.
            coords_grad = torch.zeros(n, ctx.coords_width, dtype=values.dtype)
            coords_grad.index_add_(1, columns, per_plane.view(n, 2 * groups))
        return (grads if ctx.needs_input_grad[0] else None), coords_grad, None, None


def channels_first(samples: Float[Tensor, "G N C"]) -> Float[Tensor, "G C 1 N"]:
    """[G, N, C] samples as the sampler's [G, C, 1, N], a view: the compiled sampler and
    products keep a point's channels adjacent, and pass them on so without a copy."""
    return samples.permute(0, 2, 1).unsqueeze(2)


def channels_last(samples: Float[Tensor, "G C 1 N"]) -> Float[Tensor, "G N C"]:
    """`channels_first` undone: a view where `samples` came from it, else a copy."""
    return samples.squeeze(2).transpose(1, 2).contiguous()

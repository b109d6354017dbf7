"""Small tensor operations shared across dyngs."""

from __future__ import annotations

import math

import torch
from jaxtyping import Bool, Int
from torch import Tensor


def gather(values: Tensor, index: Int[Tensor, ...]) -> Tensor:
    """values[index] for an index of any shape, through index_select.

    Its backward adds rows one after another; advanced indexing's backward adds them in
    parallel on CPUs, in an order that changes from run to run, so training would not be
    reproducible.
    """
    return values.index_select(0, index.reshape(-1)).view(*index.shape, *values.shape[1:])


def finite_rows(*tensors: Tensor) -> Bool[Tensor, " N"]:
    """Rows (along the first dimension, shared by all tensors) in which every entry of every
    tensor is finite; no gradient.

    On the CPU it first asks each tensor whether it is finite throughout: the smallest and
    largest entries are finite exactly when every entry is (`aminmax` propagates NaN, and
    an infinity is its own extreme). One pass, ~10 µs a tensor, against ~80 µs for the
    row-wise test below, whose reductions over narrow rows are slow; a training step asks
    this of every canonical parameter about three times (docs/TRAINING.md). Only when
    some entry is not finite are the rows told apart, by `finite_rows_by_row`. On a GPU
    the question would be a host sync, so it goes to the row-wise test directly.
    """
    n = tensors[0].shape[0]
    if all(t.device.type == "cpu" and _all_finite(t) for t in tensors):
        return torch.ones(n, dtype=torch.bool)
    return finite_rows_by_row(*tensors)


def _all_finite(tensor: Tensor) -> bool:
    """Whether every entry of `tensor` is finite (true of an empty one)."""
    if tensor.numel() == 0:
        return True
    low, high = torch.aminmax(tensor.detach())
    return math.isfinite(low.item()) and math.isfinite(high.item())


def finite_rows_by_row(*tensors: Tensor) -> Bool[Tensor, " N"]:
    """`finite_rows`, each row tested: the same as `torch.isfinite(t).all(dim=1)` over the
    row-flattened tensors. x·0 is ±0 for a finite x and NaN for ±Inf or NaN, so a row is
    finite exactly when its sum of x·0 is zero (a sum of zeros cannot overflow).
    `isfinite` builds three temporaries per tensor; this builds one (timings in
    docs/RENDERER.md).
    """
    n = tensors[0].shape[0]
    # An explicit row width, not -1: reshape cannot infer -1 for an empty scene (N = 0).
    zeros = [t.detach().reshape(n, math.prod(t.shape[1:])) * 0 for t in tensors]
    return torch.cat(zeros, dim=1).sum(dim=1) == 0


def zero_nonfinite(values: Tensor) -> Tensor:
    """`values` with ±Inf and NaN replaced by 0; the gradient passes where values are
    finite (`torch.where(torch.isfinite(values), values, 0)`, in one pass)."""
    return torch.nan_to_num(values, nan=0.0, posinf=0.0, neginf=0.0)

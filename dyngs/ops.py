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

    The same as `torch.isfinite(t).all(dim=1)` over the row-flattened tensors: x·0 is ±0
    for a finite x and NaN for ±Inf or NaN, so a row is finite exactly when its sum of x·0
    is zero (a sum of zeros cannot overflow). `isfinite` builds three temporaries per
    tensor; this builds one (timings in docs/RENDERER.md).
    """
    n = tensors[0].shape[0]
    # An explicit row width, not -1: reshape cannot infer -1 for an empty scene (N = 0).
    zeros = [t.detach().reshape(n, math.prod(t.shape[1:])) * 0 for t in tensors]
    return torch.cat(zeros, dim=1).sum(dim=1) == 0


def zero_nonfinite(values: Tensor) -> Tensor:
    """`values` with ±Inf and NaN replaced by 0; the gradient passes where values are
    finite (`torch.where(torch.isfinite(values), values, 0)`, in one pass)."""
    return torch.nan_to_num(values, nan=0.0, posinf=0.0, neginf=0.0)

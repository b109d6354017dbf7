"""Small tensor operations shared across dyngs."""

from __future__ import annotations

from jaxtyping import Int
from torch import Tensor


def gather(values: Tensor, index: Int[Tensor, ...]) -> Tensor:
    """values[index] for an index of any shape, through index_select.

    Its backward adds rows one after another; advanced indexing's backward adds them in
    parallel on CPUs, in an order that changes from run to run, so training would not be
    reproducible.
    """
    return values.index_select(0, index.reshape(-1)).view(*index.shape, *values.shape[1:])

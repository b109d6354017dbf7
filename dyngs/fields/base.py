"""The field protocol: features of a point in space and time.

Letters: N points, F feature channels, R resolution along a plane axis, T along time.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Protocol

from jaxtyping import Float
from torch import Tensor, nn


@dataclass
class PlaneGrids:
    """The learnable 2D grids of a plane-based field, for the regularizers.

    Spatial planes are [F, R1, R0]; time planes are [F, T, R] with time along dim -2,
    so temporal smoothness is a second difference along dim -2. Fields without planes
    (the MLP field) return empty lists and plane regularizers cost nothing.
    """

    spatial: list[Tensor] = field(default_factory=list)
    temporal: list[Tensor] = field(default_factory=list)


class Field(Protocol):
    """Features at world positions and times. Implementations are `torch.nn.Module`s that
    normalise space by their scene box and map t ∈ [0, 1] to [-1, 1] themselves."""

    out_dim: int

    def __call__(
        self, xyz: Float[Tensor, "N 3"], t: Float[Tensor, "N 1"]
    ) -> Float[Tensor, "N F"]: ...

    def planes(self) -> PlaneGrids: ...

    def parameters(self, recurse: bool = True) -> Iterator[nn.Parameter]: ...

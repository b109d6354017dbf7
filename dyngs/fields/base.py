"""The field and head protocols: features of a point in space and time, and the deltas
that deform a Gaussian from them.

A field is chosen by its config (`field:NAME`, registered in `dyngs.fields.FIELDS`), a
frozen dataclass whose `build(box, *, generator)` returns the field (`FieldSpec`); a
deformation head likewise (`HeadSpec`, `dyngs.fields.HEADS`). What only some fields can
do is a small protocol of its own, checked with isinstance: `Croppable`.

Letters: N points, F feature channels, R resolution along a plane axis, T along time.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import torch
from jaxtyping import Float
from torch import Tensor, nn

from dyngs.types import SceneBox

if TYPE_CHECKING:
    from dyngs.fields.heads import Deltas


@dataclass
class PlaneGrids:
    """The learnable 2D grids of a plane-based field, for the regularizers.

    Spatial planes are [F, R1, R0]; time planes are [F, T, R] with time along dim -2,
    so temporal smoothness is a second difference along dim -2. Fields without planes
    (the MLP field) return empty lists and plane regularizers cost nothing.
    """

    spatial: list[Tensor] = field(default_factory=list)
    temporal: list[Tensor] = field(default_factory=list)
    spatial_groups: list[Tensor] = field(default_factory=list)
    """Optional: the spatial planes as the field stores them, stacked [G, F, R1, R0], each
    plane in one group. A regularizer that reads these writes one gradient per group,
    where a plane view's gradient is a zero-filled group-sized tensor of its own."""
    temporal_groups: list[Tensor] = field(default_factory=list)
    """Optional: the time planes so, as `spatial_groups`."""
    spatial_whole: list[tuple[int, int]] = field(default_factory=list)
    """Optional: each spatial plane's [R1, R0] before the field was cut to what queries it
    (`Croppable`). The regularizers count their terms on these sizes, so cutting a plane
    leaves each kept cell's share of them unchanged. Empty: the planes as they are."""
    temporal_whole: list[tuple[int, int]] = field(default_factory=list)
    """Optional: the time planes' [T, R] so, as `spatial_whole`."""
    spatial_groups_whole: list[tuple[int, int]] = field(default_factory=list)
    """Optional: `spatial_whole` in the order of the planes in `spatial_groups`."""
    temporal_groups_whole: list[tuple[int, int]] = field(default_factory=list)
    """Optional: `temporal_whole` in the order of the planes in `temporal_groups`."""


class Field(Protocol):
    """Features at world positions and times. Implementations are `torch.nn.Module`s that
    normalise space by their scene box and map t ∈ [0, 1] to [-1, 1] themselves."""

    out_dim: int

    def __call__(
        self, xyz: Float[Tensor, "N 3"], t: Float[Tensor, "N 1"]
    ) -> Float[Tensor, "N F"]: ...

    def planes(self) -> PlaneGrids: ...

    def parameters(self, recurse: bool = True) -> Iterator[nn.Parameter]: ...


class FieldSpec(Protocol):
    """A field's config: a frozen dataclass (its docstrings are the `--help` texts) that
    builds the field for a scene box, drawing any random initial values from
    `generator`."""

    def build(self, box: SceneBox, *, generator: torch.Generator | None = None) -> Field: ...


@runtime_checkable
class Croppable(Protocol):
    """A field that can drop the storage no Gaussian queries (`crop_to`): used when a
    synchronised capture's split starts from its pixels, to cut the field to the span of
    the dynamic Gaussians before it is trained, and at the end of training."""

    def crop_to(
        self, xyz: Float[Tensor, "N 3"], trim: float = 0.0
    ) -> Callable[[Sequence[Tensor]], list[Tensor]] | None:
        """Keep what sampling at `xyz` reads (with `trim` > 0, at the points within the
        `trim` and 1 − `trim` quantiles of each axis; a point beyond then draws the field
        as still in time). Returns the map that carries tensors laid out like the old
        parameters (Adam's moments) to the new layout, or None when nothing could be
        cut."""
        ...


class Head(Protocol):
    """Turns [N, F] field features into per-Gaussian deltas (`Deltas`). Implementations are
    `torch.nn.Module`s whose outputs are exactly zero before training, so that step 0
    draws the canonical scene."""

    def __call__(self, features: Float[Tensor, "N F"]) -> Deltas: ...

    def parameters(self, recurse: bool = True) -> Iterator[nn.Parameter]: ...


class HeadSpec(Protocol):
    """A deformation head's config: builds the head for `in_dim` field features; `box`
    sets the scale of position deltas."""

    def build(
        self, in_dim: int, box: SceneBox, *, generator: torch.Generator | None = None
    ) -> Head: ...

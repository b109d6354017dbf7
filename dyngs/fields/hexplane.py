"""`field:hexplane`: six 2D feature planes per scale, sampled bilinearly and multiplied.

Letters: N points, F feature channels per plane and scale, S scales, G planes of one shape
sampled together, R resolution along a plane axis, T along time.

The factorisation of 4D space-time into the six planes xy, xz, yz, xt, yt, zt is HexPlane
(Cao & Johnson 2023) and K-Planes (Fridovich-Keil et al. 2023); the multi-scale layout,
its defaults and the deformation road it feeds are 4D Gaussian Splatting (Wu et al. 2024).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor, nn

from dyngs.compiled import numba_available, run_kernel, thread_count
from dyngs.errors import ConfigError
from dyngs.fields._common import space_time
from dyngs.fields.base import PlaneGrids
from dyngs.fields.plane_sampler import channels_first, channels_last, sample_group
from dyngs.types import DataScale, SceneBox

PLANE_AXES: tuple[tuple[int, int], ...] = ((0, 1), (0, 2), (1, 2), (0, 3), (1, 3), (2, 3))
"""The coordinate pair (a, b) of each plane in canonical order xy, xz, yz, xt, yt, zt, with
axes 0, 1, 2, 3 = x, y, z, t. Plane (a, b) is stored [F, R_b, R_a]: a runs along dim -1
(grid_sample's x) and b along dim -2, so time planes have time along dim -2."""
DEFAULT_RESOLUTION = (64, 64, 64, 25)
"""The grid size used when no data sized it (4DGaussians' D-NeRF default)."""
PIXELS_PER_CELL = 4.0
"""A data-sized grid cell spans about this many pixels at the scene centre: as fine as
the images can inform and no finer (the deformation field is smooth; the Gaussians carry
the detail)."""
SPATIAL_LIMITS = (8, 128)
TIME_LIMITS = (2, 150)
_SPATIAL_PLANES = 3
"""The first three planes of PLANE_AXES are spatial, the last three hold time."""


@dataclass(frozen=True)
class HexPlaneConfig:
    """Multi-scale HexPlane / K-Planes feature field (4D Gaussian Splatting, Wu et al. 2024)."""

    resolution: tuple[int, int, int, int] | None = None
    """Grid size along x, y, z and t at the coarsest scale. None: sized from the data
    (`sized_for`): about 4 pixels per cell at the scene centre, and in time one cell per
    two timestamps when three or more views see each time, one per six when one does
    (`time_cells`); (64, 64, 64, 25) when built without data (4DGaussians' default)."""
    multires: tuple[int, ...] = (1, 2)
    """Spatial resolution multiplier of each scale (4DGaussians' D-NeRF preset); time is never
    multiplied (Wu et al. 2024)."""
    features: int | None = None
    """Feature channels per plane and scale; the field outputs features × len(multires).
    None: sized from the data (`feature_channels`), 16 when one view sees each time and
    32 from two views on; 16 when built without data."""
    init_range: tuple[float, float] = (0.1, 0.5)
    """Spatial planes start uniform in this range (K-Planes); time planes start at exactly 1."""

    def __post_init__(self) -> None:
        if self.resolution is not None and (
            len(self.resolution) != 4 or any(r < 1 for r in self.resolution)
        ):
            raise ConfigError(f"--field.resolution must be 4 positive sizes, got {self.resolution}")
        if not self.multires or any(m < 1 for m in self.multires):
            raise ConfigError(f"--field.multires must be positive multipliers, got {self.multires}")
        if self.features is not None and self.features < 1:
            raise ConfigError(f"--field.features must be positive, got {self.features}")
        low, high = self.init_range
        if not (math.isfinite(low) and math.isfinite(high) and low <= high):
            raise ConfigError(
                f"--field.init-range must be finite with low ≤ high, got {low}, {high}"
            )

    def build(self, box: SceneBox, *, generator: torch.Generator | None = None) -> HexPlaneField:
        return HexPlaneField(self, box, generator=generator)

    def sized_for(self, scale: DataScale) -> HexPlaneConfig:
        """The grid sized from the data when `resolution` is None: a cell spans about
        PIXELS_PER_CELL pixels at the scene centre, and time gets `time_cells`, so
        neighbouring frames share a cell and the field interpolates between them; and the
        channels, when `features` is None, from `feature_channels`."""
        resolution = self.resolution or data_sized_resolution(scale)
        features = self.features or feature_channels(scale)
        return dataclasses.replace(self, resolution=resolution, features=features)


def _clamp(value: float, limits: tuple[int, int]) -> int:
    return int(min(max(round(value), limits[0]), limits[1]))


def data_sized_resolution(scale: DataScale) -> tuple[int, int, int, int]:
    """The coarsest scale's grid size for a scene (see `HexPlaneConfig.sized_for`)."""
    cell = PIXELS_PER_CELL * scale.pixel_size
    sx, sy, sz = (_clamp(size / cell, SPATIAL_LIMITS) for size in scale.box.size)
    return (sx, sy, sz, time_cells(scale))


DEFAULT_FEATURES = 16
"""Feature channels per plane and scale when no data sized them."""
MULTI_VIEW_FEATURES = 32
"""Feature channels per plane and scale from two views of each time on (4DGaussians'
width, Wu et al. 2024)."""


def feature_channels(scale: DataScale) -> int:
    """Channels per plane and scale for a scene: 16 when one view sees each time, 32 when
    two or more do. With one view per time, as with a finer time grid (`time_cells`),
    more channels let the field fit each frame as its one viewpoint saw it: 32 lost on
    every monocular scene measured and gained on every seed of the built-in scene, two
    views of each time (docs/ACCURACY.md, "Field channels from the views of each time")."""
    return DEFAULT_FEATURES if scale.views_per_timestamp < 2 else MULTI_VIEW_FEATURES


VIEWS_FOR_FINEST_TIME = 3.0
"""Views of each time from which time gets its finest grid, a cell per two timestamps."""


def time_cells(scale: DataScale) -> int:
    """Time cells for a scene: T × min(views per timestamp, 3) / 6, so a cell per six
    timestamps when one view sees each time and a cell per two from three views on.

    4DGaussians (Wu et al. 2024) gives D-NeRF's monocular sequences of 50-200 frames 25
    time cells and DyNeRF's 300 frames of 18-21 synchronised cameras 150. With one view
    per time, a finer grid lets the time planes memorise each frame as its one viewpoint
    sees it (mujoco-close_proximity, one view per time: 27.4 dB test PSNR at 54 cells,
    32.4 dB at 18; docs/ACCURACY.md); with several, the views of a time agree on one
    shape, and the finer grid follows faster motion."""
    views = min(scale.views_per_timestamp, VIEWS_FOR_FINEST_TIME)
    return _clamp(scale.num_timestamps * views / (2 * VIEWS_FOR_FINEST_TIME), TIME_LIMITS)


class HexPlaneField(nn.Module):
    """Features of (x, y, z, t) from six learnable planes per scale.

    Each scale holds the three spatial planes xy, xz, yz and the three time planes xt, yt,
    zt. A point is normalised by the scene box to [-1, 1]³ and its time t ∈ [0, 1] to
    2t − 1; each plane is sampled bilinearly at the point's two coordinates, as
    `F.grid_sample` with align_corners=True (so -1 and 1 are the centres of the edge
    texels) does; on the CPU by the compiled `plane_sampler.sample_group`.

    Combination, as in K-Planes (Fridovich-Keil et al. 2023): within a scale the six sampled
    F-vectors are multiplied elementwise (Hadamard product); the S scales' products are
    concatenated, so `out_dim = F · S`. Multiplying rather than adding lets one plane gate
    the others (a time plane can switch a feature off at some times in one region only),
    which K-Planes found markedly better for the same parameter count.

    Initialisation: spatial planes uniform in `init_range`, time planes exactly 1 (K-Planes,
    kept by 4DGaussians). Since 1 is the identity of the product, a fresh field gives the
    purely spatial (static) feature xy·xz·yz at every t: "static" is the starting point,
    and whatever the field learns about motion is the time planes' departure from 1 —
    exactly what the temporal regularizers (smoothness along t, and the K-Planes penalty
    on |1 − plane|) look at.

    Out of range: coordinates are clamped to [-1, 1] before sampling, so a point outside
    the box (or a time outside [0, 1]) gets the feature of the nearest point on the box
    (or of the nearest end of time), stays finite, and has zero gradient along the clamped
    axis — like K-Planes' border padding, stated explicitly.

    Storage: the spatial (or time) planes of one scale that share a shape are one
    [G, F, R_b, R_a] Parameter, sampled with one batched call (at the defaults, two calls
    per scale: three 64×64 spatial planes, three 25×64 time planes).
    `planes()` returns views of those Parameters, so regularizer gradients reach them.
    Time planes are sampled as 1 + interp(plane − 1), which makes a plane of exactly 1
    give exactly 1 (see `forward`).

    Cropping: `crop_to` cuts each scale's spatial planes down to the nodes that the points
    which query the field need; `extent` (saved with the planes) records the box-normalised
    span each scale then covers, and points are mapped from it onto the cut planes. A point
    where the planes were cut away samples the kept span's face and is still in time
    (`_cut_away`). `planes()` gives each plane's size before any cut beside it, on which
    the regularizers count their terms.
    """

    out_dim: int
    features: int
    """Channels per plane and scale (the config's, or DEFAULT_FEATURES when it left them
    for the data and was built without)."""
    extent: Tensor

    def __init__(
        self,
        config: HexPlaneConfig,
        box: SceneBox,
        *,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.config = config
        self.box = box
        self.features = features = config.features or DEFAULT_FEATURES
        self.out_dim = features * len(config.multires)

        low, high = config.init_range
        planes: list[list[Tensor]] = []
        for multiplier in config.multires:
            rx, ry, rz, rt = config.resolution or DEFAULT_RESOLUTION
            res = (rx * multiplier, ry * multiplier, rz * multiplier, rt)
            scale: list[Tensor] = []
            for plane, (a, b) in enumerate(PLANE_AXES):
                data = torch.empty(features, res[b], res[a])
                if plane >= _SPATIAL_PLANES:
                    data.fill_(1.0)
                else:
                    data.uniform_(low, high, generator=generator)
                scale.append(data)
            planes.append(scale)
        # Each plane's [R_b, R_a] before any crop: the regularizers' terms are counted on
        # these, so that cutting the planes leaves each kept cell's share of them as it was.
        self._whole = [[(p.shape[1], p.shape[2]) for p in scale] for scale in planes]
        self.grids = nn.ParameterList()
        self._assemble(planes)
        # The box-normalised span [lo, hi] of x, y and z that each scale's planes cover:
        # the whole box until `crop_to` fits them to the Gaussians that use the field.
        span = torch.tensor([[-1.0] * 3, [1.0] * 3])
        self.register_buffer("extent", span.repeat(len(config.multires), 1, 1))
        # Whether each scale is cut, kept beside `extent` so that `forward` never reads a
        # device tensor to decide (a sync per call on a GPU).
        self._cropped = [False] * len(config.multires)

    def _assemble(self, planes: Sequence[Sequence[Tensor]]) -> None:
        """Store six [F, R_b, R_a] planes per scale as Parameters, those of one kind and shape
        stacked into one group that a single sampling call reads."""
        grouped, self._groups, self._where, columns = _group(planes)
        device = grouped[0].device
        for name in [n for n in self._buffers if n.startswith("columns")]:
            del self._buffers[name]
        for groups in self._groups:
            for index, name, _ in groups:
                self.register_buffer(name, torch.tensor(columns[index], device=device),
                                     persistent=False)  # fmt: skip
        self.grids = nn.ParameterList(nn.Parameter(data) for data in grouped)

    def normalize(self, xyz: Float[Tensor, "N 3"], t: Float[Tensor, "N 1"]) -> Float[Tensor, "N 4"]:
        """Grid coordinates (x, y, z, t): box-normalised space and 2t − 1, clamped to [-1, 1]."""
        return space_time(self.box, xyz, t).clamp(-1.0, 1.0)

    def forward(self, xyz: Float[Tensor, "N 3"], t: Float[Tensor, "N 1"]) -> Float[Tensor, "N F"]:
        full = self.normalize(xyz, t)
        samples: list[list[Tensor]] = []  # per scale, its groups' [G, F, 1, N] samples
        for s, groups in enumerate(self._groups):
            coords = full if not self._cropped[s] else self._local(full, s)
            away = None if not self._cropped[s] else _cut_away(full, self.extent[s])
            samples.append([])
            for index, name, is_time in groups:
                # Time planes are sampled as 1 + interp(plane − 1), equal to interp(plane)
                # in exact arithmetic. The four bilinear weights do not sum to exactly 1 in
                # floating point, so a plane of ones sampled directly gives 1 ± 1 ulp,
                # varying with t; this form gives exactly 1, so the static start is exact,
                # and small departures from 1 keep their full relative precision.
                shift = 1.0 if is_time else 0.0
                sampled = sample_group(self.grids[index], coords, self.get_buffer(name), shift)
                if is_time and away is not None:
                    sampled = torch.where(away, 1.0, sampled)
                samples[-1].append(sampled)
        if full.device.type == "cpu" and numba_available():
            return compiled_products(samples)
        return plane_products(samples)

    def _local(self, coords: Float[Tensor, "N 4"], scale: int) -> Float[Tensor, "N 4"]:
        """Coordinates in scale `scale`'s planes: its [lo, hi] span mapped to [-1, 1]."""
        lo, hi = self.extent[scale].to(coords.dtype)
        xyz = ((coords[:, :3] - lo) / (hi - lo) * 2.0 - 1.0).clamp(-1.0, 1.0)
        return torch.cat((xyz, coords[:, 3:]), dim=1)

    def crop_to(
        self, xyz: Float[Tensor, "N 3"], trim: float = 0.0
    ) -> Callable[[Sequence[Tensor]], list[Tensor]] | None:
        """Keep, at every scale, only the grid nodes that bilinear sampling at `xyz` reads
        (with `trim` > 0: at the points between the `trim` and 1 − `trim` quantiles of each
        axis; those beyond sample the kept span's faces, as points beyond the box sample
        its faces, and are still in time: `_cut_away`).

        The field then costs storage only where the Gaussians that query it are (the
        dynamic ones: static Gaussians never query it), and its value at every point inside
        the kept span is unchanged: the kept nodes are the same nodes, and a cropped plane
        maps its span's ends onto its edge nodes. Points outside the box were clamped to
        its faces before, and still are. Time is never cropped.

        Returns the map from tensors laid out like `grids` (Adam's moments) to the cropped
        layout, or None when nothing could be cut.
        """
        if len(xyz) == 0:
            return None
        space = self.normalize(xyz, xyz.new_zeros(1, 1))[:, :3]
        # The order statistics at or beyond the quantiles, the least and the greatest when
        # `trim` is 0 (kthvalue: torch.quantile takes at most 16 million values).
        end = len(space) - 1
        low, high = math.floor(trim * end) + 1, math.ceil((1.0 - trim) * end) + 1
        wanted = torch.stack((space.kthvalue(low, 0).values, space.kthvalue(high, 0).values))
        nodes: list[list[tuple[int, int]]] = []
        for s in range(len(self._groups)):
            position = self._node_positions(s, wanted)
            first, last = position[0].floor().long(), position[1].ceil().long()
            sizes = self._spatial_sizes(s)
            nodes.append([_node_range(int(first[k]), int(last[k]), sizes[k]) for k in range(3)])
        return self._crop_nodes(nodes)

    def _node_positions(self, scale: int, span: Float[Tensor, "2 3"]) -> Float[Tensor, "2 3"]:
        """Where a box-normalised [lo, hi] span falls on one scale's x, y and z grid nodes
        (node i at position i), in float64."""
        lo, hi = self.extent[scale].double().cpu()
        sizes = torch.tensor(self._spatial_sizes(scale), dtype=torch.float64)
        return (span.double().cpu() - lo) / (hi - lo) * (sizes - 1)

    def _spatial_sizes(self, scale: int) -> tuple[int, int, int]:
        """Grid nodes along x, y and z at one scale (read off the xy and xz planes)."""
        xy, xz = (self.grids[i][slot] for i, slot in self._where[scale][:2])
        return xy.shape[-1], xy.shape[-2], xz.shape[-2]

    def _crop_nodes(
        self, nodes: list[list[tuple[int, int]]]
    ) -> Callable[[Sequence[Tensor]], list[Tensor]] | None:
        """Keep nodes first..last (inclusive) of each scale's x, y and z axes."""
        if all(
            (first, last) == (0, size - 1)
            for s, ranges in enumerate(nodes)
            for (first, last), size in zip(ranges, self._spatial_sizes(s), strict=True)
        ):
            return None
        where = self._where

        def cropped_planes(tensors: Sequence[Tensor]) -> list[list[Tensor]]:
            planes = []
            for s, scale in enumerate(where):
                kept = []
                for plane, (index, slot) in enumerate(scale):
                    data = tensors[index][slot]
                    a, b = PLANE_AXES[plane]
                    if b < 3:
                        data = data[:, nodes[s][b][0] : nodes[s][b][1] + 1]
                    data = data[:, :, nodes[s][a][0] : nodes[s][a][1] + 1]
                    kept.append(data.detach().clone())
                planes.append(kept)
            return planes

        def crop(tensors: Sequence[Tensor]) -> list[Tensor]:
            return _group(cropped_planes(tensors))[0]

        with torch.no_grad():
            for s, ranges in enumerate(nodes):
                # Node arithmetic on the CPU in float64, whatever device the field is on.
                lo, hi = self.extent[s].double().cpu()
                sizes = torch.tensor(self._spatial_sizes(s), dtype=torch.float64)
                kept = torch.tensor(ranges, dtype=torch.float64).T  # [2, 3]: first, last
                step = (hi - lo) / (sizes - 1)
                self.extent[s] = (lo + step * kept).to(self.extent)
                self._cropped[s] = bool((self.extent[s].abs() != 1.0).any())
            self._assemble(cropped_planes(list(self.grids)))
        return crop

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # type: ignore[no-untyped-def]
        # A checkpoint of a cropped field: crop this (full) one to the same nodes first, so
        # the shapes match. Checkpoints from before cropping existed have no extent.
        extent = state_dict.get(prefix + "extent")
        if extent is not None and not torch.equal(extent.cpu(), self.extent.cpu()):
            nodes = []
            for s in range(len(self._groups)):
                index = self._node_positions(s, extent[s]).round().long()
                nodes.append([(int(index[0, k]), int(index[1, k])) for k in range(3)])
            self._crop_nodes(nodes)
        elif extent is None:
            state_dict[prefix + "extent"] = self.extent.clone()
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def planes(self) -> PlaneGrids:
        """Views of the planes: spatial [F, R_b, R_a] in order xy, xz, yz and temporal
        [F, T, R] in order xt, yt, zt, scale after scale (coarsest first); with the
        stacked groups and every plane's size before any cut (`_plane_grids`)."""
        return _plane_grids(list(self.grids), self._where, self._groups, self._whole)

    def extra_repr(self) -> str:
        c = self.config
        return (
            f"resolution={c.resolution or DEFAULT_RESOLUTION}, multires={c.multires}, "
            f"features={self.features}, out_dim={self.out_dim}"
        )


def _plane_grids(
    grids: Sequence[Tensor],
    where: list[list[tuple[int, int]]],
    groups: list[list[tuple[int, str, bool]]],
    whole: list[list[tuple[int, int]]],
) -> PlaneGrids:
    """A HexPlane's `PlaneGrids`: its plane views in canonical order (`where[s][plane]` is
    each plane's (group, slot)), its stacked groups, and each plane's size before any cut
    (`whole[s][plane]`) in both orders."""
    views: tuple[list[Tensor], list[Tensor]] = ([], [])  # spatial, temporal
    sizes: tuple[list[tuple[int, int]], list[tuple[int, int]]] = ([], [])
    for s, places in enumerate(where):
        for plane, (index, slot) in enumerate(places):
            views[plane >= _SPATIAL_PLANES].append(grids[index][slot])
            sizes[plane >= _SPATIAL_PLANES].append(whole[s][plane])
    at = {place: (s, plane) for s, places in enumerate(where)
          for plane, place in enumerate(places)}  # fmt: skip
    stacked: tuple[list[Tensor], list[Tensor]] = ([], [])
    stacked_sizes: tuple[list[tuple[int, int]], list[tuple[int, int]]] = ([], [])
    for scale_groups in groups:
        for index, _, is_time in scale_groups:
            stacked[is_time].append(grids[index])
            for slot in range(len(grids[index])):
                s, plane = at[(index, slot)]
                stacked_sizes[is_time].append(whole[s][plane])
    return PlaneGrids(
        spatial=views[0], temporal=views[1], spatial_groups=stacked[0],
        temporal_groups=stacked[1], spatial_whole=sizes[0], temporal_whole=sizes[1],
        spatial_groups_whole=stacked_sizes[0], temporal_groups_whole=stacked_sizes[1],
    )  # fmt: skip


def _cut_away(coords: Float[Tensor, "N 4"], extent: Float[Tensor, "2 3"]) -> Tensor:
    """[N] whether each point lies where a scale's planes were cut away: beyond a face of
    its kept span `extent` ([lo, hi], box-normalised) that is not the box's own. There the
    field is still in time: a point samples the kept span's face in space and 1 on the
    time planes, as a region no Gaussian trained keeps its time planes at their starting
    1, so that what lies there cannot move by the kept span's motion."""
    lo, hi = extent.to(coords.dtype)
    xyz = coords[:, :3]
    return ((xyz < lo) & (lo > -1.0) | (xyz > hi) & (hi < 1.0)).any(dim=1)


def plane_products(samples: Sequence[Sequence[Tensor]]) -> Float[Tensor, "N SF"]:
    """Each scale's six sampled planes multiplied in order, ((((p0·p1)·p2)·p3)·p4)·p5,
    and the S products side by side: [N, S·F]. `samples` holds, per scale, its groups'
    [G, F, 1, N] samples (`HexPlaneField.forward`). The reference in PyTorch operations,
    used off the CPU; `compiled_products` is the same to the bit."""
    scales: list[Tensor] = []
    for groups in samples:
        product: Tensor | None = None
        for sampled in groups:
            # unbind, not indexing: its backward stacks the G gradients once instead of
            # zero-filling a [G, F, 1, N] tensor per plane.
            for part in sampled.unbind(0):
                product = part if product is None else product * part
        assert product is not None  # every scale has six planes
        channels, _, n = product.shape
        scales.append(product.view(channels, n).t())
    # S × [N, F] (transposed views) -> [N, S·F], one copy.
    return torch.cat(scales, dim=1)


def compiled_products(samples: Sequence[Sequence[Tensor]]) -> Float[Tensor, "N SF"]:
    """`plane_products` in one compiled pass each way (`product_kernels`), on the CPU."""
    flat = [sampled for groups in samples for sampled in groups]
    return _PlaneProduct.apply(len(samples), *flat)


class _PlaneProduct(torch.autograd.Function):
    """The [G, F, 1, N] samples of every scale's plane groups → their per-scale products
    side by side, [N, S·F]. The kernels work channels last: samples from the compiled
    sampler are so already (`plane_sampler.channels_first` views), others are copied, and
    the gradients go back as such views."""

    @staticmethod
    def forward(ctx, scales: int, *flat: Tensor) -> Tensor:  # type: ignore[override]
        from dyngs.fields import product_kernels

        samples = [channels_last(sampled.detach()) for sampled in flat]
        channels, n = flat[0].shape[1], flat[0].shape[-1]
        out = torch.empty(n, scales * channels, dtype=flat[0].dtype)
        run_kernel(product_kernels.product_forward, thread_count(None), str(out.dtype),
                   _planes(samples, scales), out.numpy())  # fmt: skip
        ctx.scales = scales
        ctx.save_for_backward(*samples)
        return out

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        from dyngs.fields import product_kernels

        samples = ctx.saved_tensors
        grads = tuple(torch.empty_like(sampled) for sampled in samples)
        upstream = grad.contiguous()
        run_kernel(product_kernels.product_backward, thread_count(None), str(upstream.dtype),
                   _planes(samples, ctx.scales), upstream.numpy(),
                   _planes(grads, ctx.scales))  # fmt: skip
        return (None, *(channels_first(g) for g in grads))


def _planes(samples: Sequence[Tensor], scales: int) -> tuple[np.ndarray, ...]:
    """The [G, N, F] samples of `scales` scales as every scale's six planes in turn,
    [N, F] arrays (views), in the order they multiply."""
    planes: list[np.ndarray] = []
    for sampled in samples:
        assert sampled.is_contiguous()  # a reshaped copy would lose the kernels' writes
        planes.extend(sampled.numpy())
    assert len(planes) == len(PLANE_AXES) * scales  # every scale has six planes
    return tuple(planes)


def _node_range(first: int, last: int, size: int) -> tuple[int, int]:
    """first..last clipped to the grid, at least two nodes (a cell) wide."""
    first, last = min(max(first, 0), size - 1), min(max(last, 0), size - 1)
    if last == first:
        first, last = (first - 1, last) if last == size - 1 else (first, last + 1)
    return first, last


def _group(
    planes: Sequence[Sequence[Tensor]],
) -> tuple[
    list[Tensor], list[list[tuple[int, str, bool]]], list[list[tuple[int, int]]], list[list[int]]
]:
    """Stack each scale's planes of one kind and shape into one tensor.

    Returns the stacked tensors; per scale, the groups as (index into the tensors, name of
    its coordinate-column buffer, whether it holds time planes); per scale and plane, its
    (group index, position in the group); and per group, the coordinate columns its
    planes read, [a0, b0, a1, b1, ...]. Spatial and time planes never share a group
    (time planes are sampled as departures from 1), and spatial groups come first, so the
    spatial product is formed before it meets the time planes.
    """
    stacked: list[Tensor] = []
    groups: list[list[tuple[int, str, bool]]] = []
    where: list[list[tuple[int, int]]] = []
    columns: list[list[int]] = []
    for scale in planes:
        by_kind_shape: dict[tuple[bool, int, int], list[int]] = {}
        for plane, data in enumerate(scale):
            key = (plane >= _SPATIAL_PLANES, data.shape[-2], data.shape[-1])
            by_kind_shape.setdefault(key, []).append(plane)
        position: dict[int, tuple[int, int]] = {}
        scale_groups: list[tuple[int, str, bool]] = []
        for (is_time, *_), members in by_kind_shape.items():
            for slot, plane in enumerate(members):
                position[plane] = (len(stacked), slot)
            scale_groups.append((len(stacked), f"columns{len(stacked)}", is_time))
            stacked.append(torch.stack([scale[plane] for plane in members]))
            columns.append([axis for plane in members for axis in PLANE_AXES[plane]])
        groups.append(scale_groups)
        where.append([position[plane] for plane in range(len(PLANE_AXES))])
    return stacked, groups, where, columns

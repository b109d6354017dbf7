"""`cpu-reference`: a tile-based Gaussian rasterizer in pure PyTorch.

This is the specification every other renderer is held to, and the renderer of every
machine without a GPU. Autograd does the backward, so forward and backward obey the same
guards by construction.

Letters: N Gaussians, V visible Gaussians, M tile–Gaussian intersections, C tiles in a
chunk, K Gaussians per tile (padded), P pixels per tile, H×W image.

The road, per camera:
1. `prepare` and `project` (`dyngs.renderers.stages`, shared with the other renderers
   that project in PyTorch): EWA splatting (Zwicker et al. 2001) as in 3D Gaussian
   Splatting (Kerbl et al. 2023): camera-space means, 2D covariance J W Σ Wᵀ Jᵀ with the
   off-axis clamp, +0.3 px² dilation (0.1 when antialiased), culling, and a per-axis
   screen extent that holds every pixel where α ≥ 1/255 (so binning into tiles never
   changes the image).
2. `rasterize`: bin into tiles, sort each tile's Gaussians by depth, and composite front
   to back over all tiles at once, chunked so that tiles of similar depth complexity are
   padded together.

Geometry (projection, the quadratic form of each Gaussian–pixel pair) is computed in
float64 whatever the input dtype: it costs little next to compositing, and it keeps
float32 renders within 1e-5 of a float64 oracle even for small Gaussians far from the
image origin. Compositing runs in the input dtype.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from jaxtyping import Float, Int
from torch import Tensor

from dyngs.errors import ConfigError
from dyngs.ops import gather
from dyngs.renderers.base import AntialiasedConfig, Guards, RenderOutput
from dyngs.renderers.stages import (
    GEOMETRY_DTYPE,
    ScreenGaussians,
    TileBins,
    bin_tiles,
    finish_image,
    pixel_range,
    project,
)
from dyngs.types import Camera, Gaussians

# A padded slot's exponent row: α = exp(-1e4) = 0, so it is skipped like any α < 1/255.
_PAD_EXPONENT = -1e4


@dataclass(frozen=True)
class CpuReferenceConfig(AntialiasedConfig):
    """The pure-PyTorch tile rasterizer (any device, float32 or float64)."""

    tile_size: int | None = None
    """Tile edge in pixels; Gaussians are binned and depth-sorted per tile. The image does not
    depend on it. None chooses 4, 8 or 16 per frame, whichever `choose_tile_size` expects
    to be fastest for the sizes of that frame's Gaussians (docs/RENDERER.md)."""
    chunk_elements: int = 1 << 20
    """Gaussian–pixel pairs composited per chunk; bounds the size of each temporary."""

    def __post_init__(self) -> None:
        if self.tile_size is not None and self.tile_size < 1:
            raise ConfigError(f"--renderer.tile-size must be ≥ 1 (or None), got {self.tile_size}")
        if self.chunk_elements < 1:
            raise ConfigError(f"--renderer.chunk-elements must be ≥ 1, got {self.chunk_elements}")

    def build(self) -> CpuReferenceRenderer:
        return CpuReferenceRenderer(self)


class CpuReferenceRenderer:
    """`prepare` → `project` → `rasterize`, all in PyTorch; autograd does the backward.
    `contribution=True` (or `with_contribution`) also measures each Gaussian's
    contribution."""

    def __init__(self, config: CpuReferenceConfig | None = None, guards: Guards | None = None):
        self.config = config or CpuReferenceConfig()
        self.guards = guards or Guards()

    def __call__(
        self,
        gaussians: Gaussians,
        camera: Camera,
        background: Float[Tensor, 3],
        *,
        contribution: bool = False,
    ) -> RenderOutput:
        screen = project(gaussians, camera, self.guards, antialiased=self.config.antialiased)
        if screen.means2d.requires_grad:
            screen.means2d.retain_grad()
        weights = (
            torch.zeros(len(gaussians), dtype=screen.colors.dtype, device=screen.colors.device)
            if contribution
            else None
        )
        absgrad = (
            torch.zeros(len(gaussians), 2, dtype=GEOMETRY_DTYPE, device=screen.colors.device)
            if screen.means2d.requires_grad
            else None
        )
        rgb, alpha, depth = rasterize(
            screen,
            camera.width,
            camera.height,
            background,
            guards=self.guards,
            tile_size=self.config.tile_size,
            chunk_elements=self.config.chunk_elements,
            contribution=weights,
            absgrad=absgrad,
        )
        return RenderOutput(
            rgb=rgb,
            alpha=alpha,
            depth=depth,
            means2d=screen.means2d,
            radii=torch.where(screen.visible[:, None], screen.extents.ceil(), 0).int(),
            visible=screen.visible,
            num_nonfinite=screen.num_nonfinite,
            contribution=weights,
            means2d_absgrad=absgrad,
        )

    def with_contribution(
        self, gaussians: Gaussians, camera: Camera, background: Float[Tensor, 3]
    ) -> RenderOutput:
        """As a call, with each Gaussian's contribution measured (`ContributionRenderer`)."""
        return self(gaussians, camera, background, contribution=True)


# Compositing costs about (pixel, Gaussian) pairs plus this many times the (tile, Gaussian)
# pairs: each pair is binned, sorted and gathered, and its exponent's coefficients are
# built once for all its tile's pixels. Least squares over 74 frames of seven trained
# models, each drawn at all three sizes, gave 11.3 (benchmarks/calibrate_tiles.py); any
# value from 8 to 16 chose about equally well.
_PAIR_COST = 12
_TILE_SIZES = (4, 8, 16)


def tile_pair_counts(
    screen: ScreenGaussians, width: int, height: int, tile_sizes: Sequence[int]
) -> list[int]:
    """How many (tile, Gaussian) pairs binning makes at each tile size."""
    visible = screen.visible.nonzero().squeeze(1)
    lo, hi = pixel_range(screen.means2d.detach()[visible], screen.extents[visible], width, height)
    return [int((hi // size - lo // size + 1).prod(dim=1).sum()) for size in tile_sizes]


def choose_tile_size(screen: ScreenGaussians, width: int, height: int) -> int:
    """The tile size in `_TILE_SIZES` with the least expected compositing work, pairs ×
    (`_PAIR_COST` + pixels per tile). Small tiles waste fewer pixels on small Gaussians
    (at 8×8, more than half of all pixel pairs of the trained demo lay outside their
    Gaussian's α ≥ 1/255 ellipse), large tiles make fewer pairs of large Gaussians."""
    counts = tile_pair_counts(screen, width, height, _TILE_SIZES)
    costs = [n * (_PAIR_COST + size * size) for n, size in zip(counts, _TILE_SIZES, strict=True)]
    return _TILE_SIZES[costs.index(min(costs))]


def _tile_pixel_basis(tile_size: int, device: torch.device) -> Float[Tensor, "P 6"]:
    """Monomials (x², xy, y², x, y, 1) of pixel centres relative to the tile centre, so the
    quadratic form ½ dᵀQd of every pair in a tile is one small matmul."""
    offsets = torch.arange(tile_size, device=device, dtype=GEOMETRY_DTYPE) + 0.5 - tile_size / 2
    py, px = torch.meshgrid(offsets, offsets, indexing="ij")
    px, py = px.reshape(-1), py.reshape(-1)
    return torch.stack((px * px, px * py, py * py, px, py, torch.ones_like(px)), dim=-1)


def _exponent_rows(
    means: Float[Tensor, "C K 2"], conics: Float[Tensor, "C K 3"], log_opacity: Float[Tensor, "C K"]
) -> Float[Tensor, "C K 6"]:
    """Coefficients ψ with ψ · (x², xy, y², x, y, 1) = ln o − ½ (p − m)ᵀ Q (p − m), the log
    of the unclamped α of a pixel p (negated here, so compositing starts with one exp)."""
    mx, my = means.unbind(-1)
    a, b, c = conics.unbind(-1)
    qx, qy = a * mx + b * my, b * mx + c * my
    const = log_opacity - 0.5 * (mx * qx + my * qy)
    return torch.stack((-0.5 * a, -b, -0.5 * c, qx, qy, const), dim=-1)


def rasterize(
    screen: ScreenGaussians,
    width: int,
    height: int,
    background: Float[Tensor, 3],
    guards: Guards | None = None,
    tile_size: int | None = None,
    chunk_elements: int = 1 << 20,
    contribution: Float[Tensor, " N"] | None = None,
    absgrad: Float[Tensor, "N 2"] | None = None,
) -> tuple[Float[Tensor, "H W 3"], Float[Tensor, "H W 1"], Float[Tensor, "H W 1"]]:
    """Composite projected Gaussians front to back; returns rgb, alpha and expected depth.

    When `contribution` is given, each Gaussian's blending weights summed over the pixels
    are added to it in place (without gradient); when `absgrad` is, backward adds Σ over
    pixels of |∂L/∂means2d| per axis to it. `tile_size` None: `choose_tile_size`.
    """
    guards = guards or Guards()
    tile_size = tile_size or choose_tile_size(screen, width, height)
    dtype, device = screen.colors.dtype, screen.colors.device
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    pixels = tile_size * tile_size
    bins = bin_tiles(screen, width, height, tile_size)

    # Per-Gaussian quantities blended with the same weights: colour, depth, and 1 (alpha).
    blended = torch.cat(
        (
            screen.colors,
            screen.depths.to(dtype)[:, None],
            screen.colors.new_ones(len(screen.colors), 1),
        ),
        dim=1,
    )
    basis = _tile_pixel_basis(tile_size, device)
    log_opacity = screen.opacities.clamp_min(1e-30).log()
    pad_row = torch.zeros(6, dtype=GEOMETRY_DTYPE, device=device)
    pad_row[5] = _PAD_EXPONENT

    tiles = torch.argsort(bins.tile_count, descending=True, stable=True)
    counts = bins.tile_count[tiles].tolist()
    outputs, done_tiles = [], []
    for start, stop in _chunks(counts, chunk_elements // pixels):
        chunk = tiles[start:stop]
        outputs.append(
            _composite_chunk(
                screen, bins, chunk, counts[start], tiles_x, tile_size, basis,
                log_opacity, pad_row, blended, guards, contribution, (width, height),
                absgrad,
            )
        )  # fmt: skip
        done_tiles.append(chunk)

    if not outputs:
        # Nothing to draw: an empty copy keeps the image attached to the inputs, so a
        # training step on an empty view still runs backward (and yields zero gradients).
        outputs.append(blended[:0, None, :].expand(0, pixels, -1))
        done_tiles.append(tiles[:0])
    accum = blended.new_zeros(tiles_x * tiles_y, pixels, blended.shape[1])
    accum = accum.index_copy(0, torch.cat(done_tiles), torch.cat(outputs))
    return _image(accum, tiles_y, tiles_x, tile_size, width, height, background)


def _image(
    accum: Float[Tensor, "T P 5"],
    tiles_y: int,
    tiles_x: int,
    tile_size: int,
    width: int,
    height: int,
    background: Float[Tensor, 3],
) -> tuple[Float[Tensor, "H W 3"], Float[Tensor, "H W 1"], Float[Tensor, "H W 1"]]:
    """Per-tile sums of weighted (colour, depth, 1) laid out as an image: rgb over the
    background, alpha, and expected depth."""
    image = (
        accum.view(tiles_y, tiles_x, tile_size, tile_size, -1)
        .permute(0, 2, 1, 3, 4)
        .reshape(tiles_y * tile_size, tiles_x * tile_size, -1)[:height, :width]
    )
    return finish_image(image, background)


# A chunk pads every tile to the depth complexity of its busiest one; it ends before a tile
# with fewer than this share of that many Gaussians. Padding then stays under a third of
# the real work, while the number of chunks (each costs ~25 small tensor operations)
# grows only with the log of the depth-complexity range. 0.75 was fastest of 0-0.8 on the
# trained demo and MuJoCo models (docs/RENDERER.md); without it, padding doubled the work
# on scenes whose few busiest tiles hold most Gaussians.
_CHUNK_FILL = 0.75


def _chunks(counts: list[int], budget: int) -> list[tuple[int, int]]:
    """Split tiles sorted by descending Gaussian count into [start, stop) ranges that are
    padded together: at most `budget` padded pairs each (one tile at least), and no tile
    with under `_CHUNK_FILL` of the first one's count. Empty tiles are left out."""
    busy = sum(1 for n in counts if n > 0)
    ranges, start = [], 0
    while start < busy:
        depth = counts[start]
        stop = min(busy, start + max(1, budget // depth))
        floor = _CHUNK_FILL * depth
        stop = next((j for j in range(start + 1, stop) if counts[j] < floor), stop)
        ranges.append((start, stop))
        start = stop
    return ranges


def zero_below(x: Tensor, floor: float) -> Tensor:
    """`x` where x ≥ `floor` (compared in x's dtype), 0 elsewhere; the gradient passes where
    x is kept. The same values and gradient as `x.masked_fill(x < floor, 0)`, bit for bit,
    without a boolean mask: `F.threshold` keeps x > θ, and θ here is the largest number of
    x's dtype below `floor`. It is faster than `masked_fill` on CPUs, which pays for
    building and reading a boolean mask (timings in docs/RENDERER.md)."""
    level = torch.tensor(floor, dtype=x.dtype)
    theta = torch.nextafter(level, torch.tensor(-math.inf, dtype=x.dtype))
    return F.threshold(x, float(theta), 0.0)


def _composite_chunk(
    screen: ScreenGaussians,
    bins: TileBins,
    tiles: Int[Tensor, " C"],
    depth_complexity: int,
    tiles_x: int,
    tile_size: int,
    basis: Float[Tensor, "P 6"],
    log_opacity: Float[Tensor, " N"],
    pad_row: Float[Tensor, 6],
    blended: Float[Tensor, "N F"],
    guards: Guards,
    contribution: Float[Tensor, " N"] | None = None,
    image_size: tuple[int, int] = (0, 0),
    absgrad: Float[Tensor, "N 2"] | None = None,
) -> Float[Tensor, "C P F"]:
    """Front-to-back compositing of every pixel of `tiles`, each padded to K Gaussians."""
    slot = torch.arange(depth_complexity, device=tiles.device)
    count = bins.tile_count[tiles][:, None]
    real = slot < count  # [C, K]
    index = bins.tile_start[tiles][:, None] + torch.minimum(slot, count - 1)
    gid = bins.gaussian[index]  # [C, K]

    centre = (
        torch.stack(((tiles % tiles_x) * tile_size, (tiles // tiles_x) * tile_size), dim=-1).to(
            GEOMETRY_DTYPE
        )
        + tile_size / 2
    )
    means = gather(screen.means2d, gid) - centre[:, None]
    conics = gather(screen.conics, gid)
    rows = _exponent_rows(means, conics, gather(log_opacity, gid))
    rows = torch.where(real[..., None], rows, pad_row)
    # Pixels × Gaussians with Gaussians last: the scan along depth then runs over
    # contiguous memory, several times faster than along a middle dimension.
    exponent = (basis @ rows.transpose(1, 2)).to(blended.dtype)  # [C, P, K]: ln o − ½ dᵀQd
    if absgrad is not None and exponent.requires_grad:
        exponent = _AbsGradTap.apply(
            exponent, absgrad, gid, real, means.detach(), conics.detach(), basis
        )
    if guards.alpha_min > 0:
        # exp is about ten times slower on arguments far below its underflow (padded slots
        # and far pixels reach -1e4). Every pair under ln(alpha_min) is dropped just below,
        # so raising those arguments to just under it changes neither image nor gradient.
        exponent = exponent.clamp_min(math.log(guards.alpha_min) - 1)

    alpha = torch.exp(exponent).clamp_max(guards.alpha_max)
    if guards.alpha_min > 0:
        alpha = zero_below(alpha, guards.alpha_min)
    transmit = torch.cumprod(1 - alpha, dim=2)  # transmittance after each Gaussian
    before = torch.cat((torch.ones_like(transmit[..., :1]), transmit[..., :-1]), dim=2)
    weight = alpha * before
    if guards.transmittance_min > 0:
        # Transmittance only falls, so "stop before T would drop below the floor" is exactly
        # "drop every pair whose T after it is below the floor". The sign of the kept T is
        # that 0/1 mask; multiplying by it is exact (× 1 or × 0) and has no gradient.
        weight = weight * zero_below(transmit.detach(), guards.transmittance_min).sign()
    if contribution is not None:
        _add_contribution(contribution, weight.detach(), gid, tiles, tiles_x, tile_size, image_size)
    return weight @ gather(blended, gid)


class _AbsGradTap(torch.autograd.Function):
    """The identity on the exponents ψ = ln o − ½ dᵀQd [C, P, K], whose backward also adds
    Σ over pixels of |∂L/∂means2d| to a per-Gaussian sink (AbsGS, Ye et al. 2024). A pair's
    share of ∂L/∂means2d is ∂L/∂ψ · Q d with d = p − m: the gradient summed per pixel before
    the pixels are summed, which autograd alone never shows."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        exponent: Tensor,
        sink: Tensor,
        gid: Tensor,
        real: Tensor,
        means: Tensor,
        conics: Tensor,
        basis: Tensor,
    ) -> Tensor:
        ctx.sink = sink
        ctx.save_for_backward(gid, real, means, conics, basis)
        return exponent.view_as(exponent)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        gid, real, means, conics, basis = ctx.saved_tensors
        g = grad.to(GEOMETRY_DTYPE)
        dx = basis[None, :, 3, None] - means[:, None, :, 0]  # [C, P, K]
        dy = basis[None, :, 4, None] - means[:, None, :, 1]
        a, b, c = (conics[:, None, :, i] for i in range(3))
        per_axis = torch.stack(
            ((g * (a * dx + b * dy)).abs().sum(1), (g * (b * dx + c * dy)).abs().sum(1)), dim=-1
        )  # [C, K, 2]
        ctx.sink.index_put_((gid[real],), per_axis[real], accumulate=True)
        return grad, None, None, None, None, None, None


def _add_contribution(
    contribution: Float[Tensor, " N"],
    weight: Float[Tensor, "C P K"],
    gid: Int[Tensor, "C K"],
    tiles: Int[Tensor, " C"],
    tiles_x: int,
    tile_size: int,
    image_size: tuple[int, int],
) -> None:
    """Add each Gaussian's blending weights, summed over the pixels of `tiles` that lie
    inside the image (edge tiles overhang it), to `contribution`. Padded slots have zero
    weight, so adding them to their stand-in row is harmless."""
    local = torch.arange(tile_size, device=tiles.device)
    cols = (tiles % tiles_x)[:, None] * tile_size + local
    rows = (tiles // tiles_x)[:, None] * tile_size + local
    inside = (rows[:, :, None] < image_size[1]) & (cols[:, None, :] < image_size[0])
    inside = inside.reshape(len(tiles), -1, 1).to(weight.dtype)
    per_pair = (weight * inside).sum(dim=1).reshape(-1).to(contribution.dtype)
    contribution.index_add_(0, gid.reshape(-1), per_pair)

"""The stages every renderer shares: `prepare` (finiteness cull, near/far, the camera in
float64), then `project` (EWA splatting onto the image plane) for the renderers that
project in PyTorch. A renderer is these stages plus a rasterizer that composites.

Letters: N Gaussians, K SH coefficients per channel.

`prepare` is where the guards that do not depend on the rasterizer live, so that every
renderer makes the same decisions:
- a Gaussian with a NaN or ±Inf in a parameter it uses (mean, quaternion, scale,
  opacity, a colour coefficient of the degree in use) is zeroed *before* any arithmetic,
  so that neither it nor its gradient (0·NaN = NaN) can leak into the rest of the scene,
  then culled and counted;
- means go to camera space in float64 whatever the input dtype, and a Gaussian at depth
  ≤ near or ≥ far is culled;
- `relative_means` gives the means relative to the camera centre in float64: the
  difference of nearby points is exact there, where float32 would lose ~1e-3 units of a
  scene 1e4 units from the origin (docs/NUMERICS.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from dyngs.geometry import covariance_3d
from dyngs.ops import finite_rows
from dyngs.renderers.base import Guards
from dyngs.sh import eval_sh, eval_sh0
from dyngs.types import Camera, Gaussians

GEOMETRY_DTYPE = torch.float64

# The extent is widened by this much (relative, then absolute in px) so that rounding
# never leaves out a pixel whose α reaches the threshold; a wider extent costs a few
# skipped pairs and never changes the image.
_EXTENT_RELATIVE_MARGIN = 1e-4
_EXTENT_ABSOLUTE_MARGIN = 1e-3


@dataclass
class Prepared:
    """Gaussians made safe to draw from one camera: non-finite rows zeroed, geometry in
    float64 (gradients flow back to the input parameters through every tensor here)."""

    means: Float[Tensor, "N 3"]
    """World-space means, float64."""
    quats: Float[Tensor, "N 4"]
    scales: Float[Tensor, "N 3"]
    opacities: Float[Tensor, " N"]
    """float64; not yet zeroed for depth (renderers cull by `in_depth` themselves)."""
    colors: Float[Tensor, "N 3"] | Float[Tensor, "N K 3"]
    """RGB, or the SH coefficients of the degree in use, in the input dtype."""
    finite: Bool[Tensor, " N"]
    """Rows whose every used parameter is finite."""
    rotation: Float[Tensor, "3 3"]
    translation: Float[Tensor, " 3"]
    camera_means: Float[Tensor, "N 3"]
    """Means in camera space (OpenCV axes), R μ + t in float64."""
    in_depth: Bool[Tensor, " N"]
    """near < depth < far."""
    num_nonfinite: Int[Tensor, ""]

    @property
    def center(self) -> Float[Tensor, " 3"]:
        """The camera centre in world space, −Rᵀt (float64)."""
        return -self.rotation.T @ self.translation

    def relative_means(self) -> Float[Tensor, "N 3"]:
        """Means relative to the camera centre, μ − c, in float64."""
        return self.means - self.center

    def seen_colors(self, sh_degree: int | None, dtype: torch.dtype) -> Float[Tensor, "N 3"]:
        """RGB as the camera sees it: `colors` as they are (`sh_degree` None), or their SH
        along each mean's direction from the camera centre, in `dtype`."""
        if sh_degree is None:
            return self.colors
        if sh_degree == 0:
            return eval_sh0(self.colors)  # no view direction needed
        # View directions from the float64 camera-relative means: in float32 a scene 1e4
        # units from the origin would shift SH colours by up to 1e-3 against the oracle.
        # Only the (short) result is rounded to the input dtype.
        return eval_sh(sh_degree, self.colors, self.relative_means().to(dtype))


def prepare(gaussians: Gaussians, camera: Camera) -> Prepared:
    """The first stage of every renderer (see the module docstring)."""
    g = gaussians
    dtype = GEOMETRY_DTYPE
    used = g.colors if g.sh_degree is None else g.colors[:, : (g.sh_degree + 1) ** 2]
    finite = finite_rows(g.means, g.quats, g.scales, g.opacities, used)
    keep = finite[:, None]
    means = torch.where(keep, g.means, 0).to(dtype)
    w2c = camera.world_to_camera.to(device=g.means.device, dtype=dtype)
    rotation, translation = w2c[:3, :3], w2c[:3, 3]
    camera_means = means @ rotation.T + translation
    depth = camera_means[:, 2]
    return Prepared(
        means=means,
        quats=torch.where(keep, g.quats, 0).to(dtype),
        scales=torch.where(keep, g.scales, 0).to(dtype),
        opacities=torch.where(finite, g.opacities, 0).to(dtype),
        colors=torch.where(finite.view(-1, *[1] * (used.ndim - 1)), used, 0),
        finite=finite,
        rotation=rotation,
        translation=translation,
        camera_means=camera_means,
        in_depth=(depth > camera.near) & (depth < camera.far),
        num_nonfinite=(~finite).sum(),
    )


@dataclass
class ScreenGaussians:
    """Gaussians projected onto one image: everything `rasterize` needs."""

    means2d: Float[Tensor, "N 2"]
    conics: Float[Tensor, "N 3"]
    """Inverse of the dilated 2D covariance as (a, b, c): [[a, b], [b, c]]."""
    opacities: Float[Tensor, " N"]
    depths: Float[Tensor, " N"]
    colors: Float[Tensor, "N 3"]
    extents: Float[Tensor, "N 2"]
    """Half-widths in px of the box holding every pixel centre where α ≥ alpha_min."""
    visible: Bool[Tensor, " N"]
    num_nonfinite: Int[Tensor, ""]
    """How many Gaussians were culled for a NaN or ±Inf parameter (0-d, on the device)."""


def project(
    gaussians: Gaussians, camera: Camera, guards: Guards, antialiased: bool = False
) -> ScreenGaussians:
    """Project Gaussians onto the image plane of `camera` (EWA splatting), from `prepare`."""
    g = gaussians
    ready = prepare(gaussians, camera)
    opacities, finite = ready.opacities, ready.finite
    x, y, z = ready.camera_means.unbind(-1)
    z = torch.where(ready.in_depth, z, 1.0)  # culled rows never divide by a tiny or negative depth

    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    means2d = torch.stack((fx * x / z + cx, fy * y / z + cy), dim=-1)
    a, b, c = covariance_2d(x, y, z, ready, camera, guards)
    dilation = guards.dilation(antialiased)
    a_d, c_d = a + dilation, c + dilation
    det = a_d * c_d - b * b
    if antialiased:
        ratio = (a * c - b * b).clamp_min(0) / det.clamp_min(1e-30)
        # √'s gradient is infinite at 0, where a degenerate 2D covariance (or one whose
        # determinant rounding took to 0) puts the compensation: there it gets none, as in
        # the compiled projection, instead of 0 · ∞ = NaN in every parameter behind it.
        positive = ratio > 0
        compensation = torch.where(positive, torch.where(positive, ratio, 1.0).sqrt(), 0.0)
        opacities = opacities * compensation
    # Finite float64 parameters can still overflow here (scales beyond ~1e120 make det
    # inf, and then a conic entry is inf / inf = NaN). Such rows are culled, as the oracle
    # does; a finite det implies finite a_d, b, c_d and so a finite conic.
    valid = finite & ready.in_depth & (det > 0) & (opacities >= guards.alpha_min)
    valid &= finite_rows(det, means2d)
    det = torch.where(valid, det, 1.0)
    conics = torch.stack((c_d / det, -b / det, a_d / det), dim=-1)

    with torch.no_grad():
        # α ≥ alpha_min  ⟺  dᵀ Σ⁻¹ d ≤ 2 ln(o / alpha_min): an ellipse whose bounding box
        # has half-widths √(2 ln(o / alpha_min) Σ_xx) and √(… Σ_yy).
        level = 2 * torch.log(torch.where(valid, opacities / guards.alpha_min, 1.0))
        extents = (level.clamp_min(0)[:, None] * torch.stack((a_d, c_d), -1).clamp_min(0)).sqrt()
        extents = extents * (1 + _EXTENT_RELATIVE_MARGIN) + _EXTENT_ABSOLUTE_MARGIN
        lo, hi = pixel_range(means2d, extents, camera.width, camera.height)
        visible = valid & (lo <= hi).all(dim=-1)
        extents = torch.where(visible[:, None], extents, 0)

    rgb = ready.seen_colors(g.sh_degree, g.means.dtype)
    return ScreenGaussians(
        means2d=means2d,
        conics=conics,
        opacities=torch.where(valid, opacities, 0),
        depths=z,
        colors=rgb,
        extents=extents,
        visible=visible,
        num_nonfinite=ready.num_nonfinite,
    )


def off_axis_limits(camera: Camera, guards: Guards) -> tuple[float, float, float, float]:
    """How far x/z may go left and right, and y/z up and down, in the EWA Jacobian: to the
    image's edges and (off_axis − 1)·tan(fov/2) beyond them on each side.

    Kerbl et al. 2023 clamp at ±1.3·tan(fov/2) about the optical axis. Measured from the
    image's edges, as gsplat does, the bounds are the same for a centred principal point
    and follow an off-centre one, so every renderer here draws what gsplat draws."""
    margin_x = (guards.off_axis - 1) * 0.5 * camera.width / camera.fx
    margin_y = (guards.off_axis - 1) * 0.5 * camera.height / camera.fy
    return (
        camera.cx / camera.fx + margin_x,
        (camera.width - camera.cx) / camera.fx + margin_x,
        camera.cy / camera.fy + margin_y,
        (camera.height - camera.cy) / camera.fy + margin_y,
    )


def covariance_2d(
    x: Float[Tensor, " N"],
    y: Float[Tensor, " N"],
    z: Float[Tensor, " N"],
    ready: Prepared,
    camera: Camera,
    guards: Guards,
) -> tuple[Float[Tensor, " N"], Float[Tensor, " N"], Float[Tensor, " N"]]:
    """The screen-space covariance J W Σ Wᵀ Jᵀ (EWA, Zwicker et al. 2001) of Gaussians at
    camera-space (x, y, z), as its entries (a, b, c) = (Σxx, Σxy, Σyy), before dilation.
    Culled rows' z must already be replaced, so that nothing divides by a tiny or negative
    depth."""
    fx, fy = camera.fx, camera.fy
    # The Jacobian of the perspective map sees the centre clamped to a little beyond the
    # image, so Gaussians far off-axis do not get enormous, unstable footprints.
    left, right, top, bottom = off_axis_limits(camera, guards)
    tx = (x / z).clamp(-left, right) * z
    ty = (y / z).clamp(-top, bottom) * z
    zeros = torch.zeros_like(z)
    jac = torch.stack(
        (fx / z, zeros, -fx * tx / (z * z), zeros, fy / z, -fy * ty / (z * z)), dim=-1
    ).reshape(-1, 2, 3)
    t = jac @ ready.rotation
    cov2d = t @ covariance_3d(ready.quats, ready.scales, guards.quat_eps) @ t.transpose(1, 2)
    return cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]


def pixel_range(
    means2d: Float[Tensor, "N 2"], extents: Float[Tensor, "N 2"], width: int, height: int
) -> tuple[Int[Tensor, "N 2"], Int[Tensor, "N 2"]]:
    """Inclusive (column, row) index range of pixel centres inside each box, clipped to the
    image; empty when lo > hi."""
    size = torch.tensor([width, height], device=means2d.device, dtype=means2d.dtype)
    # Pixel j's centre is j + 0.5. Clamping in float first keeps huge boxes from
    # overflowing the integer conversion.
    lo = torch.ceil(torch.minimum((means2d - extents - 0.5).clamp_min(-1), size)).long()
    hi = torch.floor(torch.minimum((means2d + extents - 0.5).clamp_min(-1), size)).long()
    limit = size.long() - 1
    return lo.clamp_min(0), torch.minimum(hi, limit)


@dataclass
class TileBins:
    """Tile–Gaussian intersections (M of them over T tiles), sorted by tile, then by depth
    within a tile: tile t's Gaussians, front to back, are
    `gaussian[tile_start[t] : tile_start[t] + tile_count[t]]`."""

    gaussian: Int[Tensor, " M"]
    tile_start: Int[Tensor, " T"]
    tile_count: Int[Tensor, " T"]


def depth_order(
    screen: ScreenGaussians, width: int, height: int
) -> tuple[Int[Tensor, " V"], Int[Tensor, "V 2"], Int[Tensor, "V 2"]]:
    """The visible Gaussians front to back (a stable sort, so ties keep index order), with
    the inclusive pixel range of each one's box: what binning into tiles starts from."""
    visible = screen.visible.nonzero().squeeze(1)
    order = visible[torch.argsort(screen.depths.detach()[visible], stable=True)]
    lo, hi = pixel_range(screen.means2d.detach()[order], screen.extents[order], width, height)
    return order, lo, hi


def bin_tiles(screen: ScreenGaussians, width: int, height: int, tile_size: int) -> TileBins:
    """Every visible Gaussian in every tile its extent box touches, in depth order. The
    stage between `project` and compositing for the tile rasterizers."""
    tiles_x = -(-width // tile_size)
    tiles_y = -(-height // tile_size)
    device = screen.means2d.device
    order, lo, hi = depth_order(screen, width, height)
    t_lo, t_hi = lo // tile_size, hi // tile_size
    span = t_hi - t_lo + 1  # [V, 2] tiles along x and y
    per_gaussian = span[:, 0] * span[:, 1]
    owner = torch.repeat_interleave(torch.arange(len(order), device=device), per_gaussian)
    rank = torch.arange(len(owner), device=device) - (per_gaussian.cumsum(0) - per_gaussian)[owner]
    tile_x = t_lo[owner, 0] + rank % span[owner, 0]
    tile_y = t_lo[owner, 1] + rank // span[owner, 0]
    tile = tile_y * tiles_x + tile_x
    # A stable sort by tile keeps the global depth order inside every tile.
    tile, perm = torch.sort(tile, stable=True)
    count = torch.bincount(tile, minlength=tiles_x * tiles_y)
    start = count.cumsum(0) - count
    return TileBins(gaussian=order[owner[perm]], tile_start=start, tile_count=count)


def finish_image(
    sums: Float[Tensor, "H W 5"], background: Float[Tensor, " 3"]
) -> tuple[Float[Tensor, "H W 3"], Float[Tensor, "H W 1"], Float[Tensor, "H W 1"]]:
    """The last stage of the tile rasterizers: per-pixel sums of the blending weights times
    (colour, depth, 1) become rgb over the background, alpha (Σ w) and expected depth
    (Σ w z / Σ w; 0 where nothing is drawn)."""
    color, depth_sum, alpha = sums[..., :3], sums[..., 3:4], sums[..., 4:5]
    rgb = color + (1 - alpha) * background.to(dtype=sums.dtype, device=sums.device)
    depth = depth_sum / alpha.clamp_min(torch.finfo(sums.dtype).tiny)
    return rgb, alpha, depth

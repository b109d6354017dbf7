"""The renderer protocol and the data it exchanges.

Letters used in shapes: N Gaussians, H×W image.

A renderer is one call: Gaussians, a camera and a background colour in; an image and
the per-Gaussian screen-space data that densification needs out. Every renderer obeys
the numerical guards below (docs/DESIGN.md), in forward and backward alike, and starts
from the same `prepare` stage (`dyngs.renderers.stages`).

A renderer is chosen by its config (`renderer:NAME`, registered in
`dyngs.renderers.RENDERERS`), a frozen dataclass whose `build()` returns it
(`RendererSpec`). What only some renderers can do is a protocol of its own, checked with
isinstance: `ContributionRenderer`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from jaxtyping import Bool, Float, Int
from torch import Tensor

from dyngs.types import Camera, Gaussians

__all__ = [
    "AntialiasedConfig",
    "Camera",
    "ContributionRenderer",
    "Gaussians",
    "Guards",
    "RenderOutput",
    "Renderer",
    "RendererSpec",
]


@dataclass(frozen=True)
class Guards:
    """Numerical guards shared by every renderer (the table in docs/DESIGN.md)."""

    eps2d: float = 0.3
    """Added to the diagonal of every 2D covariance, in px², by the plain rule (the low-pass
    filter of Kerbl et al. 2023, drawn at full opacity)."""
    mip_filter: float = 0.1
    """Takes `eps2d`'s place when the renderer is antialiased: the variance, in px², of
    Mip-Splatting's 2D filter (Yu et al. 2024; 0.1 in its code), a Gaussian stand-in for the
    box filter of one pixel's area (whose variance is 1/12 px²). The opacity compensation
    keeps the filter from adding mass, so it only has to band-limit: 0.3 px² would widen
    every Gaussian to a σ of at least 0.55 px, blurring what area-sampled images show sharp
    (docs/ACCURACY.md, "Mip-Splatting's filter width")."""
    off_axis: float = 1.3
    """The EWA Jacobian sees x/z and y/z clamped to the image's field of view widened by
    (off_axis − 1)·tan(fov/2) on each side: ±1.3·tan(fov/2) for a centred principal point, as
    in Kerbl et al. 2023, and the bounds gsplat uses for any principal point."""
    alpha_min: float = 1.0 / 255.0
    """A Gaussian–pixel pair whose α is below this is skipped."""
    alpha_max: float = 0.99
    """α is clamped to at most this, so transmittance never reaches zero (Kerbl et al. 2023)."""
    transmittance_min: float = 1e-4
    """Compositing stops before transmittance would fall below this."""
    quat_eps: float = 1e-12
    """Quaternions are normalised by max(|q|, quat_eps); a zero quaternion means no rotation."""

    def dilation(self, antialiased: bool) -> float:
        """The px² added to every 2D covariance's diagonal: `mip_filter` when the renderer is
        antialiased, `eps2d` when it draws 3DGS's plain rule."""
        return self.mip_filter if antialiased else self.eps2d


ABSENT_BELOW = Guards().alpha_min
"""A Gaussian whose temporal presence at t is under every renderer's α floor draws nothing
at t (its opacity is at most its presence), so drawing may leave it undeformed there
(`DynamicGaussians.at(absent_below=ABSENT_BELOW)`): the same pixels and gradients."""


@dataclass(frozen=True)
class AntialiasedConfig:
    """The base of the built-in renderers' configs: the one drawing rule they all offer both
    ways, so that its `--help` text is written once (a plugin renderer may derive from it)."""

    antialiased: bool = True
    """Mip-Splatting's 2D filter (Yu et al. 2024): add its 0.1 px² (`Guards.mip_filter`) to
    every 2D covariance and scale opacity by √(det Σ / det(Σ + 0.1 I)), which band-limits a
    small Gaussian to the pixel grid without adding to its mass, as a pixel that integrates
    light over its area sees it. On by default (docs/ACCURACY.md); `--renderer.no-antialiased`
    draws 3DGS's rule instead: 0.3 px² dilation (`Guards.eps2d`) at full opacity."""


@dataclass
class RenderOutput:
    """What a renderer returns for one camera."""

    rgb: Float[Tensor, "H W 3"]
    alpha: Float[Tensor, "H W 1"]
    depth: Float[Tensor, "H W 1"]
    """Expected depth along the optical axis, Σ wᵢzᵢ / Σ wᵢ; 0 where nothing is drawn."""
    means2d: Float[Tensor, "N 2"]
    """Projected centres in pixels. Retains its gradient after backward when the inputs
    require grad, for densification by screen-space gradient."""
    radii: Int[Tensor, "N 2"]
    """Per-axis screen extent in whole pixels; 0 where a Gaussian is not drawn."""
    visible: Bool[Tensor, " N"]
    """True for every Gaussian that can touch at least one pixel."""
    num_nonfinite: Int[Tensor, ""]
    """How many Gaussians had a NaN or ±Inf in a parameter (mean, quaternion, scale,
    opacity or a colour coefficient in use) and were culled: drawn nowhere, with zero
    gradient. A 0-d integer tensor on the render device, so that producing it never
    waits for the device; the caller decides when to read it."""
    contribution: Float[Tensor, " N"] | None = None
    """Each Gaussian's blending weight αT summed over the image's pixels (no gradient): how
    much of the picture it makes, for pruning by importance. Measured only by
    `ContributionRenderer.with_contribution`; None otherwise."""
    means2d_absgrad: Float[Tensor, "N 2"] | None = None
    """Σ over pixels of |∂L/∂means2d| per axis, filled in by backward (AbsGS, Ye et al. 2024):
    unlike the gradient, per-pixel terms of opposite sign do not cancel, so a Gaussian
    blurring fine detail still asks to be split. None where the renderer cannot measure it."""


class Renderer(Protocol):
    """Draws Gaussians from one camera over a background colour."""

    def __call__(
        self, gaussians: Gaussians, camera: Camera, background: Float[Tensor, 3]
    ) -> RenderOutput: ...


@runtime_checkable
class ContributionRenderer(Protocol):
    """A renderer that can also measure each Gaussian's contribution to the picture
    (`RenderOutput.contribution`), which pruning by importance needs. It costs a pass
    over every Gaussian–pixel pair, so only pruning asks for it."""

    def __call__(
        self, gaussians: Gaussians, camera: Camera, background: Float[Tensor, 3]
    ) -> RenderOutput: ...

    def with_contribution(
        self, gaussians: Gaussians, camera: Camera, background: Float[Tensor, 3]
    ) -> RenderOutput:
        """As a call, with `RenderOutput.contribution` measured."""
        ...


class RendererSpec(Protocol):
    """A renderer's config: a frozen dataclass (its docstrings are the `--help` texts)
    whose `build()` returns the renderer, or raises `RendererUnavailable` saying what
    this machine lacks."""

    def build(self) -> Renderer: ...

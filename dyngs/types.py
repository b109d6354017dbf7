"""The data every stage of dyngs exchanges: a pinhole camera and a set of Gaussians.

Letters used in shapes: N Gaussians, K spherical-harmonic coefficients per channel.

Conventions (docs/DESIGN.md): cameras are OpenCV (x right, y down, z forward), given as a
world-to-camera 4×4 matrix; pixel centres sit at +0.5, so pixel (row i, column j) is
the point (j + 0.5, i + 0.5) on the image plane.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Protocol, runtime_checkable

import torch
from jaxtyping import Float
from torch import Tensor

NEAR_PLANE = 0.01
"""Default near plane: Gaussians at depth ≤ this are culled (the guard table of docs/DESIGN.md)."""


@dataclass(frozen=True)
class Camera:
    """A pinhole camera in the OpenCV convention."""

    fx: float
    fy: float
    cx: float
    cy: float
    world_to_camera: Float[Tensor, "4 4"]
    width: int
    height: int
    near: float = NEAR_PLANE
    far: float = 1e10

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise ValueError(f"camera image size must be positive, got {self.width}×{self.height}")
        if not (math.isfinite(self.fx) and math.isfinite(self.fy) and self.fx > 0 and self.fy > 0):
            raise ValueError(
                f"camera focal lengths must be finite and positive, got {self.fx}, {self.fy}"
            )
        if not (math.isfinite(self.cx) and math.isfinite(self.cy)):
            raise ValueError(f"camera principal point must be finite, got {self.cx}, {self.cy}")
        if not 0 < self.near < self.far:
            raise ValueError(f"camera needs 0 < near < far, got near={self.near}, far={self.far}")
        if tuple(self.world_to_camera.shape) != (4, 4):
            raise ValueError(
                f"world_to_camera must be 4×4, got {tuple(self.world_to_camera.shape)}"
            )
        if not bool(torch.isfinite(self.world_to_camera).all()):
            raise ValueError("world_to_camera has non-finite entries")

    @staticmethod
    def from_fov(
        fov_x: float,
        width: int,
        height: int,
        world_to_camera: Float[Tensor, "4 4"],
        **kwargs: float,
    ) -> Camera:
        """A centred camera with square pixels and horizontal field of view `fov_x` (radians)."""
        focal = 0.5 * width / math.tan(0.5 * fov_x)
        return Camera(focal, focal, width / 2, height / 2, world_to_camera, width, height, **kwargs)

    @property
    def rotation(self) -> Float[Tensor, "3 3"]:
        return self.world_to_camera[:3, :3]

    @property
    def translation(self) -> Float[Tensor, 3]:
        return self.world_to_camera[:3, 3]

    @property
    def center(self) -> Float[Tensor, 3]:
        """Camera centre in world space, -Rᵀt."""
        return -self.rotation.T @ self.translation

    def viewpoint(self, decimals: int = 3) -> tuple[float, ...]:
        """The centre rounded to `decimals`: one key per position of a fixed rig, so that
        views from the same camera can be counted and grouped."""
        return tuple(round(float(v), decimals) for v in self.center)

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> Camera:
        return replace(self, world_to_camera=self.world_to_camera.to(device=device, dtype=dtype))

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by `factor` (e.g. 0.5 halves width and height)."""
        width = max(1, round(self.width * factor))
        height = max(1, round(self.height * factor))
        sx, sy = width / self.width, height / self.height
        return replace(
            self,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=self.cx * sx,
            cy=self.cy * sy,
            width=width,
            height=height,
        )


@dataclass
class Gaussians:
    """Activated Gaussians, ready to draw.

    `colors` is RGB [N, 3] when `sh_degree` is None, else spherical-harmonic coefficients
    [N, K, 3] with K ≥ (sh_degree + 1)², evaluated from the camera centre.
    """

    means: Float[Tensor, "N 3"]
    quats: Float[Tensor, "N 4"]
    """Rotations as quaternions (w, x, y, z); renderers normalise them again."""
    scales: Float[Tensor, "N 3"]
    """Standard deviations along the rotated axes (already exponentiated)."""
    opacities: Float[Tensor, " N"]
    colors: Float[Tensor, "N 3"] | Float[Tensor, "N K 3"]
    sh_degree: int | None = None

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        expected = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,)}
        for name, shape in expected.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"Gaussians.{name} must have shape {shape}, got {got}")
        if self.sh_degree is None:
            if tuple(self.colors.shape) != (n, 3):
                raise ValueError(
                    f"Gaussians.colors must be RGB [{n}, 3] when sh_degree is None, "
                    f"got {tuple(self.colors.shape)}"
                )
        else:
            need = (self.sh_degree + 1) ** 2
            if not 0 <= self.sh_degree <= 3:
                raise ValueError(f"sh_degree must be in 0..3, got {self.sh_degree}")
            if (
                self.colors.ndim != 3
                or self.colors.shape[0] != n
                or self.colors.shape[2] != 3
                or self.colors.shape[1] < need
            ):
                raise ValueError(
                    f"Gaussians.colors must be SH [{n}, ≥{need}, 3] for degree "
                    f"{self.sh_degree}, got {tuple(self.colors.shape)}"
                )

    def __len__(self) -> int:
        return self.means.shape[0]

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> Gaussians:
        def move(t: Tensor) -> Tensor:
            return t.to(device=device, dtype=dtype)

        return Gaussians(
            move(self.means),
            move(self.quats),
            move(self.scales),
            move(self.opacities),
            move(self.colors),
            self.sh_degree,
        )


@dataclass(frozen=True)
class SceneBox:
    """An axis-aligned box holding the scene; fields normalise space by it to [-1, 1]."""

    lower: tuple[float, float, float]
    upper: tuple[float, float, float]

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (*self.lower, *self.upper)):
            raise ValueError(f"scene box must be finite, got {self.lower}..{self.upper}")
        if not all(hi > lo for lo, hi in zip(self.lower, self.upper, strict=True)):
            raise ValueError(
                f"scene box needs upper > lower on every axis, got {self.lower}..{self.upper}"
            )

    @property
    def center(self) -> tuple[float, float, float]:
        lo, hi = self.lower, self.upper
        return (0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), 0.5 * (lo[2] + hi[2]))

    @property
    def size(self) -> tuple[float, float, float]:
        lo, hi = self.lower, self.upper
        return (hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2])

    @property
    def diagonal(self) -> float:
        return math.sqrt(sum(s * s for s in self.size))

    def normalize(self, xyz: Float[Tensor, "N 3"]) -> Float[Tensor, "N 3"]:
        """Map the box to [-1, 1]³ (points outside land outside that range)."""
        lower = xyz.new_tensor(self.lower)
        upper = xyz.new_tensor(self.upper)
        return (xyz - lower) / (upper - lower) * 2 - 1


@dataclass(frozen=True)
class DataScale:
    """What a scene's data can inform, for components that size themselves from it
    (`DataSized`): measured from the parsed scene before anything is built."""

    box: SceneBox
    pixel_size: float
    """World size of one pixel at the scene-box centre (median over training cameras)."""
    num_timestamps: int
    """Distinct training times."""
    image_pixels: int
    """Pixels of one training image."""
    viewpoints: int
    """Distinct training camera positions."""
    views: int = 0
    """Training images (0: unknown, taken as one per timestamp)."""

    @property
    def views_per_timestamp(self) -> float:
        """Training images per distinct time: 1 for a monocular sequence, the camera count
        for a synchronised multi-camera capture."""
        return max(self.views, self.num_timestamps) / max(self.num_timestamps, 1)


@runtime_checkable
class DataSized(Protocol):
    """A component config with sizes left for the data to choose (e.g. a grid resolution
    of None). `sized_for` returns the config with them filled in; a config whose sizes
    were all given returns itself. The run folder records the resolved config."""

    def sized_for(self, scale: DataScale) -> DataSized: ...

"""Renderers: `cpu-reference` (pure PyTorch, the specification), `cpu-tile` (compiled
kernels for CPUs) and `cuda-tile` (gsplat).

`RENDERERS` holds their configs by name (`renderer:cpu-reference`, `renderer:cuda-tile`);
an installed package adds its own through the `dyngs.renderers` entry-point group (see
`dyngs.registry`). `default_renderer()` picks what the machine can run, and `rasterize`
draws raw tensors with any registered renderer, without building a `Gaussians` or a
`Camera` first.

Letters: N Gaussians, K SH coefficients per channel, H×W image.
"""

from __future__ import annotations

from functools import cache

import torch
from jaxtyping import Float
from torch import Tensor

from dyngs.errors import RendererUnavailable
from dyngs.registry import Registry, is_config_class
from dyngs.renderers.base import ContributionRenderer, Renderer, RendererSpec, RenderOutput
from dyngs.renderers.cpu_reference import CpuReferenceConfig
from dyngs.renderers.cpu_tile import CpuTileConfig, cpu_tile_available
from dyngs.renderers.cuda_tile import CudaTileConfig, cuda_tile_available
from dyngs.types import NEAR_PLANE, Camera, Gaussians

RENDERERS: Registry[type[RendererSpec]] = Registry("renderer", "dyngs.renderers", is_config_class)
RENDERERS.register("cpu-reference", CpuReferenceConfig)
RENDERERS.register("cuda-tile", CudaTileConfig)
RENDERERS.register("cpu-tile", CpuTileConfig)


def renderer_name(config: RendererSpec) -> str:
    """The renderer's CLI name (`renderer:NAME`); a ConfigError for an unregistered one."""
    return RENDERERS.name_of(config)


def default_renderer() -> RendererSpec:
    """cuda-tile where a CUDA device and gsplat are present, else cpu-tile (the compiled
    CPU rasterizer, held to cpu-reference by the tests), else cpu-reference."""
    if cuda_tile_available():
        return CudaTileConfig()
    return CpuTileConfig() if cpu_tile_available() else CpuReferenceConfig()


@cache
def _built(name: str) -> Renderer:
    return RENDERERS.get(name)().build()


def rasterize(
    means: Float[Tensor, "N 3"],
    quats: Float[Tensor, "N 4"],
    scales: Float[Tensor, "N 3"],
    opacities: Float[Tensor, " N"],
    colors: Float[Tensor, "N 3"] | Float[Tensor, "N K 3"],
    world_to_camera: Float[Tensor, "4 4"],
    K: Float[Tensor, "3 3"],
    width: int,
    height: int,
    *,
    sh_degree: int | None = None,
    background: Float[Tensor, " 3"] | None = None,
    near: float = NEAR_PLANE,
    far: float = 1e10,
    renderer: str | Renderer = "cpu-reference",
    contribution: bool = False,
) -> RenderOutput:
    """Draw activated Gaussians (unit-free quaternions w, x, y, z; standard deviations;
    opacities in [0, 1]; RGB, or SH coefficients of `sh_degree`) with a pinhole camera
    (OpenCV world-to-camera, intrinsics `K`) over `background` (default black).

    `renderer` is a registered name, built with its default config, or a built renderer.
    `contribution` also measures each Gaussian's contribution, which needs a
    `ContributionRenderer`.
    """
    drawer = _built(renderer) if isinstance(renderer, str) else renderer
    gaussians = Gaussians(means, quats, scales, opacities, colors, sh_degree)
    k = K.detach().double().cpu()
    camera = Camera(
        fx=float(k[0, 0]),
        fy=float(k[1, 1]),
        cx=float(k[0, 2]),
        cy=float(k[1, 2]),
        world_to_camera=world_to_camera,
        width=width,
        height=height,
        near=near,
        far=far,
    )
    if background is None:
        background = torch.zeros(3, dtype=means.dtype, device=means.device)
    if not contribution:
        return drawer(gaussians, camera, background)
    if not isinstance(drawer, ContributionRenderer):
        raise RendererUnavailable(f"renderer {renderer!r} cannot measure contribution")
    return drawer.with_contribution(gaussians, camera, background)


__all__ = [
    "RENDERERS",
    "ContributionRenderer",
    "CpuReferenceConfig",
    "CpuTileConfig",
    "CudaTileConfig",
    "RenderOutput",
    "Renderer",
    "RendererSpec",
    "RendererUnavailable",
    "cpu_tile_available",
    "default_renderer",
    "rasterize",
    "renderer_name",
]

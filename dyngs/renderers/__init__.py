"""Renderers: `cpu-reference` (pure PyTorch, the specification) and `cuda-tile` (gsplat).

`RendererConfig` is the tagged union the CLI offers (`renderer:cpu-reference`,
`renderer:cuda-tile`); `default_renderer()` picks what the machine can run.
"""

from __future__ import annotations

from typing import Annotated, Union

import tyro

from dyngs.errors import RendererUnavailable
from dyngs.renderers.base import Renderer, RenderOutput
from dyngs.renderers.cpu_reference import CpuReferenceConfig
from dyngs.renderers.cuda_tile import CudaTileConfig, cuda_tile_available

RendererConfig = Union[  # noqa: UP007 (tyro reads the tags from this form)
    Annotated[CpuReferenceConfig, tyro.conf.subcommand("cpu-reference")],
    Annotated[CudaTileConfig, tyro.conf.subcommand("cuda-tile")],
]


def renderer_name(config: CpuReferenceConfig | CudaTileConfig) -> str:
    """The renderer's CLI name (`renderer:NAME`)."""
    return "cuda-tile" if isinstance(config, CudaTileConfig) else "cpu-reference"


def default_renderer() -> CpuReferenceConfig | CudaTileConfig:
    """cuda-tile where a CUDA device and gsplat are present, else cpu-reference."""
    return CudaTileConfig() if cuda_tile_available() else CpuReferenceConfig()


__all__ = [
    "CpuReferenceConfig",
    "CudaTileConfig",
    "RenderOutput",
    "Renderer",
    "RendererConfig",
    "RendererUnavailable",
    "default_renderer",
    "renderer_name",
]

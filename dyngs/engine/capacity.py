"""Model only what a scene needs: capacity sized from the data.

Every size that a config leaves as None is filled here from the parsed scene, before
anything is built, and the run folder records the resolved values:

- HexPlane spatial resolution: a cell spans about `PIXELS_PER_CELL` pixels at the scene
  centre, so the grid is as fine as the images can inform and no finer (the deformation
  field is smooth; the Gaussians carry the detail). Time resolution: one cell per two
  distinct timestamps, so neighbouring frames share a cell and the field interpolates.
- The Gaussian budget: about one Gaussian per image pixel, times √(distinct viewpoints)/8
  within [0.5, 3] (more views resolve more surface), and within [5k, 3M] in all. The
  initial point cloud is subsampled to it too.
"""

from __future__ import annotations

import dataclasses
import math
import statistics

import torch

from dyngs.config import TrainConfig
from dyngs.datamanagers.base import SceneData
from dyngs.fields.hexplane import HexPlaneConfig

PIXELS_PER_CELL = 4.0
SPATIAL_LIMITS = (8, 128)
TIME_LIMITS = (2, 150)
BUDGET_LIMITS = (5_000, 3_000_000)


def _clamp(value: float, limits: tuple[int, int]) -> int:
    return int(min(max(round(value), limits[0]), limits[1]))


def pixel_footprint(scene: SceneData) -> float:
    """World size of one pixel at the scene-box centre, median over training cameras."""
    center = torch.tensor(scene.scene_box.center, dtype=torch.float64)
    sizes = []
    for camera in scene.train.cameras:
        distance = float((camera.center.double().cpu() - center).norm())
        sizes.append(distance / math.sqrt(camera.fx * camera.fy))
    return statistics.median(sizes)


def hexplane_resolution(scene: SceneData) -> tuple[int, int, int, int]:
    cell = PIXELS_PER_CELL * pixel_footprint(scene)
    sx, sy, sz = (_clamp(size / cell, SPATIAL_LIMITS) for size in scene.scene_box.size)
    st = _clamp(scene.num_timestamps / 2, TIME_LIMITS)
    return (sx, sy, sz, st)


def distinct_viewpoints(scene: SceneData, decimals: int = 3) -> int:
    centers = {tuple(round(float(v), decimals) for v in c.center) for c in scene.train.cameras}
    return len(centers)


def gaussian_budget(scene: SceneData) -> int:
    camera = scene.train.cameras[0]
    pixels = camera.width * camera.height
    views = min(max(math.sqrt(distinct_viewpoints(scene)) / 8, 0.5), 3.0)
    return _clamp(pixels * views, BUDGET_LIMITS)


def resolve_capacity(config: TrainConfig, scene: SceneData) -> TrainConfig:
    """`config` with every data-sized value filled in from `scene`."""
    field = config.field
    if isinstance(field, HexPlaneConfig) and field.resolution is None:
        field = dataclasses.replace(field, resolution=hexplane_resolution(scene))
    densify = config.densify
    if densify.max_gaussians is None:
        densify = dataclasses.replace(densify, max_gaussians=gaussian_budget(scene))
    gaussians = config.gaussians
    if gaussians.max_init_points is None:  # the data-sized budget, even when it was overridden
        gaussians = dataclasses.replace(gaussians, max_init_points=gaussian_budget(scene))
    return dataclasses.replace(config, field=field, densify=densify, gaussians=gaussians)

"""Model only what a scene needs: capacity sized from the data.

Every size that a config leaves as None is filled here from the parsed scene, before
anything is built, and the run folder records the resolved values:

- Component configs that size themselves (`DataSized`, e.g. the HexPlane grid: about
  4 pixels per cell at the scene centre, half a cell per timestamp) are given the scene's
  `DataScale`.
- The step count (`training_steps`), when `--max-iters` is not given.
- The Gaussian budget: about one Gaussian per image pixel, times √(distinct viewpoints)/8
  within [0.5, 3] (more views resolve more surface), and within [5k, 3M] in all. The
  initial point cloud is subsampled to it too.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
from typing import Any

import torch

from dyngs.config import TrainConfig
from dyngs.datamanagers.base import SceneData
from dyngs.fields.hexplane import time_cells
from dyngs.types import DataScale, DataSized

BUDGET_LIMITS = (5_000, 3_000_000)


def pixel_footprint(scene: SceneData) -> float:
    """World size of one pixel at the scene-box centre, median over training cameras."""
    center = torch.tensor(scene.scene_box.center, dtype=torch.float64)
    sizes = []
    for camera in scene.train.cameras:
        distance = float((camera.center.double().cpu() - center).norm())
        sizes.append(distance / math.sqrt(camera.fx * camera.fy))
    return statistics.median(sizes)


def distinct_viewpoints(scene: SceneData, decimals: int = 3) -> int:
    return len({camera.viewpoint(decimals) for camera in scene.train.cameras})


def data_scale(scene: SceneData) -> DataScale:
    """What the scene's training data can inform (see `DataScale`)."""
    camera = scene.train.cameras[0]
    return DataScale(
        box=scene.scene_box,
        pixel_size=pixel_footprint(scene),
        num_timestamps=scene.num_timestamps,
        image_pixels=camera.width * camera.height,
        viewpoints=distinct_viewpoints(scene),
        views=len(scene.train.cameras),
    )


def gaussian_budget(scale: DataScale) -> int:
    views = min(max(math.sqrt(scale.viewpoints) / 8, 0.5), 3.0)
    low, high = BUDGET_LIMITS
    return int(min(max(round(scale.image_pixels * views), low), high))


STEPS_BASE = 3000
"""Steps every run takes: a static scene's Gaussians settle in about this many."""

STEPS_PER_TIMESTAMP = 60
"""Steps added per distinct timestamp: the deformation learns each time from the views of
it, and a time the window reaches late still needs steps of its own."""

STEPS_LIMITS = (3000, 30000)


def training_steps(scene: SceneData) -> int:
    """The data-sized `max_iters`: `STEPS_BASE` + `STEPS_PER_TIMESTAMP` per timestamp,
    within `STEPS_LIMITS`, in hundreds."""
    steps = STEPS_BASE + STEPS_PER_TIMESTAMP * scene.num_timestamps
    low, high = STEPS_LIMITS
    return int(min(max(round(steps, -2), low), high))


def training_steps_why(scene: SceneData) -> str:
    """What `training_steps` sized the run from, for the log."""
    return (
        f"{STEPS_BASE} + {STEPS_PER_TIMESTAMP} × {scene.num_timestamps} timestamps; "
        "--max-iters or --time-budget to choose"
    )


def _sized(config: Any, scale: DataScale) -> Any:
    return config.sized_for(scale) if isinstance(config, DataSized) else config


def resolve_capacity(config: TrainConfig, scene: SceneData) -> TrainConfig:
    """`config` with every data-sized value filled in from `scene`."""
    scale = data_scale(scene)
    budget = gaussian_budget(scale)
    densify = config.densify
    if densify.max_gaussians is None:
        densify = dataclasses.replace(densify, max_gaussians=budget)
    if densify.grow_min_life is None:
        densify = dataclasses.replace(densify, grow_min_life=1.0 / time_cells(scale))
    gaussians = config.gaussians
    if gaussians.max_init_points is None:  # the data-sized budget, even when it was overridden
        gaussians = dataclasses.replace(gaussians, max_init_points=budget)
    max_iters = training_steps(scene) if config.max_iters is None else config.max_iters
    return dataclasses.replace(
        config,
        max_iters=max_iters,
        field=_sized(config.field, scale),
        head=_sized(config.head, scale),
        densify=densify,
        gaussians=gaussians,
    )

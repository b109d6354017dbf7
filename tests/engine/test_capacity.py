"""Capacity sized from the data: HexPlane grid, Gaussian budget, importance pruning."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest
import torch

from dyngs.config import TrainConfig
from dyngs.datamanagers.base import SceneData
from dyngs.datamanagers.datamanager import DataConfig, load_scene
from dyngs.datamanagers.procedural import demo_path
from dyngs.engine.capacity import (
    BUDGET_LIMITS,
    data_scale,
    distinct_viewpoints,
    gaussian_budget,
    pixel_footprint,
    resolve_capacity,
)
from dyngs.engine.densify import DensifyConfig, DensifyState, plan_refinement
from dyngs.engine.trainer import Trainer
from dyngs.engine.writer import NullWriter
from dyngs.fields.hexplane import (
    HexPlaneConfig,
    data_sized_resolution,
    feature_channels,
    time_cells,
)
from dyngs.types import DataScale, SceneBox
from tests.engine.helpers import TINY_SCENE, assert_same_state, tiny_config, tiny_trainer


def _scene(**changes: Any) -> SceneData:
    return load_scene(str(demo_path(dataclasses.replace(TINY_SCENE, **changes))), DataConfig())


def test_finer_images_and_more_timestamps_give_a_finer_grid() -> None:
    coarse, fine = _scene(), _scene(resolution=64, num_times=12)
    assert abs(pixel_footprint(coarse) / pixel_footprint(fine) - 2.0) < 0.05
    rc, rf = (data_sized_resolution(data_scale(s)) for s in (coarse, fine))
    for axis in range(3):  # a cell spans the same number of pixels at both resolutions
        assert abs(rf[axis] - 2 * rc[axis]) <= 1, (rc, rf)
    assert data_scale(coarse).views_per_timestamp == 2  # TINY_SCENE: two cameras per time
    assert (rc[3], rf[3]) == (2, 4)  # two views of each time: a cell per three timestamps


@pytest.mark.parametrize(("views_per_time", "cells"), [(1, 10), (2, 20), (3, 30), (12, 30)])
def test_time_cells_follow_the_views_of_each_time(views_per_time: int, cells: int) -> None:
    """A cell per six timestamps seen once (4DGaussians' D-NeRF grids), per two from three
    views of each time on (its DyNeRF grids), in proportion between."""
    box = SceneBox(lower=(-1.0, -1.0, -1.0), upper=(1.0, 1.0, 1.0))
    scale = DataScale(box=box, pixel_size=0.01, num_timestamps=60, image_pixels=10_000,
                      viewpoints=12, views=60 * views_per_time)  # fmt: skip
    assert time_cells(scale) == cells
    assert data_sized_resolution(scale)[3] == cells
    unknown = dataclasses.replace(scale, views=0)  # counted as one view per time
    assert time_cells(unknown) == 10


@pytest.mark.parametrize(("views_per_time", "channels"), [(1, 16), (1.5, 16), (2, 32), (12, 32)])
def test_feature_channels_follow_the_views_of_each_time(
    views_per_time: float, channels: int
) -> None:
    """A monocular sequence gets 16 channels a plane, two or more views of each time 32."""
    box = SceneBox(lower=(-1.0, -1.0, -1.0), upper=(1.0, 1.0, 1.0))
    scale = DataScale(box=box, pixel_size=0.01, num_timestamps=60, image_pixels=10_000,
                      viewpoints=12, views=int(60 * views_per_time))  # fmt: skip
    assert feature_channels(scale) == channels
    sized = HexPlaneConfig().sized_for(scale)
    assert sized.features == channels
    assert sized.build(box).out_dim == channels * len(sized.multires)
    assert HexPlaneConfig(features=8).sized_for(scale).features == 8  # given: kept
    assert HexPlaneConfig().build(box).out_dim == 16 * 2  # built without data


def test_the_budget_grows_with_pixels_and_viewpoints() -> None:
    small, large = _scene(), _scene(resolution=128)
    many_views = _scene(resolution=128, views_per_time=12)
    assert distinct_viewpoints(many_views) > distinct_viewpoints(large)
    budgets = [gaussian_budget(data_scale(s)) for s in (small, large, many_views)]
    assert budgets[0] == BUDGET_LIMITS[0]  # 32² images: the floor
    assert budgets[0] < budgets[1] < budgets[2]


def test_explicit_sizes_are_kept_and_missing_ones_filled() -> None:
    scene = _scene()
    resolved = resolve_capacity(TrainConfig(), scene)
    assert isinstance(resolved.field, HexPlaneConfig)
    assert resolved.field.resolution == data_sized_resolution(data_scale(scene))
    assert resolved.field.features == feature_channels(data_scale(scene))
    assert resolved.densify.max_gaussians == gaussian_budget(data_scale(scene))
    assert resolved.gaussians.max_init_points == gaussian_budget(data_scale(scene))
    assert resolved.densify.grow_min_life == 1.0 / time_cells(data_scale(scene))
    explicit = TrainConfig(
        field=HexPlaneConfig(resolution=(5, 6, 7, 8), features=8),
        densify=DensifyConfig(max_gaussians=1234, grow_min_life=0.0),
    )
    kept = resolve_capacity(explicit, scene)
    assert kept.field == explicit.field and kept.densify.max_gaussians == 1234
    assert kept.densify.grow_min_life == 0.0


def test_gaussians_that_make_almost_nothing_of_any_view_are_pruned(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path)
    model = trainer.model
    n = len(model.canonical)
    state = DensifyState.zeros(n, trainer.device)
    state.count[:] = 3.0
    state.importance[:] = 10.0
    state.importance[:5] = 0.1  # seen, but never half a pixel's worth of a view
    state.count[5], state.importance[5] = 0.0, 0.0  # never seen in this window: kept
    config = DensifyConfig(reset_opacity_every=0, grad_threshold=1.0)
    plan = plan_refinement(config, model, state, 100, trainer.extent)
    assert plan is not None
    kept = set(plan[0].source.tolist())
    assert kept == set(range(5, n))
    off = dataclasses.replace(config, prune_importance=0.0)
    assert plan_refinement(off, model, state, 100, trainer.extent) is None


def test_with_importance_views_0_each_step_measures_importance(tmp_path: Path) -> None:
    densify = dataclasses.replace(tiny_config().densify, importance_views=0)
    trainer = tiny_trainer(tmp_path, densify=densify)
    assert trainer.lifecycle.measures_each_step(trainer.renderer)
    stats = trainer.train_step(0)
    importance = trainer.lifecycle.state.importance
    seen = trainer.lifecycle.state.count > 0
    assert bool(seen.any())
    # After one view, each Gaussian's importance is its share of that view's coverage.
    total = float(stats.out.alpha.detach().sum())
    assert total > 10.0
    assert abs(float(importance.sum()) - total) <= 1e-4 * total
    assert not bool(importance[~seen].any())


@pytest.mark.parametrize("change", [{}, {"prune_importance": 0.0}])
def test_otherwise_no_training_step_measures_importance(
    tmp_path: Path, change: dict[str, Any]
) -> None:
    """With the window's views measured before each refinement (the default), or no
    pruning by importance, nothing reads a step's contributions, so none are computed;
    the importance left in the state is +inf, "never prune by it", until measured."""
    densify = dataclasses.replace(tiny_config().densify, **change)
    trainer = tiny_trainer(tmp_path, densify=densify)
    assert not trainer.lifecycle.measures_each_step(trainer.renderer)
    stats = trainer.train_step(0)
    assert stats.out.contribution is None
    assert bool(torch.isinf(trainer.lifecycle.state.importance).all())


class AlwaysMeasures:
    """Wraps a renderer and measures contribution on every call, as all did before."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner

    def __call__(self, gaussians: Any, camera: Any, background: Any) -> Any:
        return self.inner.with_contribution(gaussians, camera, background)

    def with_contribution(self, gaussians: Any, camera: Any, background: Any) -> Any:
        return self.inner.with_contribution(gaussians, camera, background)


def test_not_measuring_contribution_changes_no_training_step(tmp_path: Path) -> None:
    """Training steps skip the measure when nothing reads it: the model after several
    refinements is bit for bit the one trained with every render measuring."""
    densify = dataclasses.replace(tiny_config().densify, refine_start=0, refine_every=4)
    states = []
    for name, measure_always in (("skips", False), ("measures", True)):
        trainer = tiny_trainer(tmp_path / name, densify=densify, max_iters=16)
        if measure_always:
            trainer.renderer = AlwaysMeasures(trainer.renderer)
        for step in range(trainer.config.steps):
            trainer.train_step(step)
            trainer.step = step + 1
        states.append(trainer.model.state_dict())
    skips, measures = states
    assert_same_state(skips, measures)


def test_a_run_too_short_to_densify_says_so(tmp_path: Path) -> None:
    def notes(max_iters: int) -> list[str]:
        return Trainer(tiny_config(max_iters=max_iters), tmp_path, NullWriter()).notes()

    assert "no densification in this run" in notes(500)[0]  # window 300 … 250: empty
    assert notes(1000) == []  # window 300 … 500

"""`--densify.importance-factor`: the importance pass renders large views shrunk and counts
each Gaussian's share in the whole view's pixels."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

from dyngs.config import CoarseConfig
from dyngs.engine import schedules
from dyngs.engine.densify import DensifyConfig
from dyngs.engine.trainer import Trainer
from dyngs.errors import ConfigError
from dyngs.renderers.base import ContributionRenderer
from dyngs.types import Camera
from tests.engine.helpers import tiny_config, tiny_trainer


def _camera(width: int, height: int) -> Camera:
    return Camera(40.0, 42.0, width / 2, height / 2, torch.eye(4), width, height)


def test_only_views_that_keep_the_coarse_min_side_shrink() -> None:
    config = tiny_config(coarse=CoarseConfig(min_side=128))
    assert config.densify.importance_factor == 2
    assert schedules.importance_factor(config, _camera(480, 270)) == 2  # 135 px kept
    assert schedules.importance_factor(config, _camera(480, 250)) == 1  # 125: too few
    assert schedules.importance_factor(config, _camera(100, 100)) == 1  # the MuJoCo scenes
    whole = dataclasses.replace(config, densify=DensifyConfig(importance_factor=1))
    assert schedules.importance_factor(whole, _camera(4000, 3000)) == 1
    # Unlike a training view, an importance view shrinks whatever the step: coarse
    # training off, or long over, leaves the pass as it is.
    off = dataclasses.replace(config, coarse=CoarseConfig(until=0.0, min_side=128))
    assert schedules.importance_factor(off, _camera(480, 270)) == 2


def test_the_factor_must_be_positive() -> None:
    with pytest.raises(ConfigError, match=r"--densify\.importance-factor must be ≥ 1"):
        DensifyConfig(importance_factor=0)


def _measure(trainer: Trainer, factor: int, step: int) -> tuple[torch.Tensor, set[tuple[int, int]]]:
    """The importance at `step` with the pass's views shrunk by `factor`, and the view
    sizes it rendered."""
    config = trainer.lifecycle.config
    densify = dataclasses.replace(config.densify, importance_factor=factor)
    trainer.lifecycle.config = dataclasses.replace(config, densify=densify)
    renderer = trainer.renderer
    assert isinstance(renderer, ContributionRenderer)
    sizes: set[tuple[int, int]] = set()
    draw = renderer.with_contribution

    def recorded(gaussians, camera, background):  # type: ignore[no-untyped-def]
        sizes.add((camera.width, camera.height))
        return draw(gaussians, camera, background)

    renderer.with_contribution = recorded  # type: ignore[method-assign]
    try:
        with torch.no_grad():
            return trainer.lifecycle.measure_importance(step, renderer), sizes
    finally:
        del renderer.with_contribution


def test_shrunk_views_measure_what_whole_ones_do_in_whole_view_pixels(tmp_path: Path) -> None:
    """On the tiny demo scene (32² views, min side lowered so that they shrink to 16²), a
    Gaussian's share of a half-size view, times the four pixels each of its pixels stands
    for, is its share of the whole view: the blending weight summed over pixels estimates
    the same integral at either pixel size. The scene's Gaussians are small, a quarter of
    a whole pixel's worth to one pixel's (the hard case for a half-size view, whose pixel
    is larger than they are); the two measures agree on them, and so do the prune
    threshold's decisions."""
    trainer = tiny_trainer(tmp_path, max_iters=40, coarse=CoarseConfig(min_side=8))
    for step in range(12):
        trainer.train_step(step)
    whole, whole_sizes = _measure(trainer, 1, 12)
    shrunk, shrunk_sizes = _measure(trainer, 2, 12)
    assert whole_sizes == {(32, 32)} and shrunk_sizes == {(16, 16)}
    seen = whole > 0.25
    assert int(seen.sum()) > 100
    ratio = shrunk[seen] / whole[seen]
    assert abs(float(ratio.median()) - 1) < 0.05
    assert float((ratio - 1).abs().quantile(0.9)) < 0.15
    threshold = trainer.config.densify.prune_importance
    differ = (whole < threshold) != (shrunk < threshold)
    assert float(differ.float().mean()) < 0.02

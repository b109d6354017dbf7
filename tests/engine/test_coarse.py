"""Coarse-to-fine training (`--coarse`): the first part of a run draws its training views
shrunk, the rest whole, and nothing else changes meaning."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

from dyngs.config import CoarseConfig, LossConfig, TrainConfig
from dyngs.datamanagers.datamanager import TrainBatch, area_resize
from dyngs.datamanagers.procedural import demo_path
from dyngs.engine import schedules
from dyngs.engine.densify import view_statistics
from dyngs.engine.lifecycle import densify_statistics
from dyngs.engine.trainer import Trainer
from dyngs.engine.writer import NullWriter
from dyngs.errors import ConfigError
from dyngs.renderers.base import RenderOutput
from dyngs.types import Camera
from tests.engine.helpers import tiny_config, tiny_trainer
from tests.engine.test_loss_weights import RIG


def _camera(width: int, height: int) -> Camera:
    return Camera(40.0, 42.0, width / 2, height / 2, torch.eye(4), width, height)


def _factor(config: TrainConfig, step: int, width: int, height: int) -> int:
    return schedules.coarse_factor(config, step, _camera(width, height))


def _batch(width: int, height: int, masked: bool = True) -> TrainBatch:
    generator = torch.Generator().manual_seed(0)
    image = torch.rand(height, width, 3, generator=generator)
    mask = torch.rand(height, width, 1, generator=generator) if masked else None
    return TrainBatch(_camera(width, height), 0.25, image, mask, 7)


def test_the_schedule_shrinks_large_views_until_its_fraction_of_the_run() -> None:
    config = tiny_config(max_iters=100, coarse=CoarseConfig(until=0.3, factor=2, min_side=16))
    factor = _factor
    assert [factor(config, step, 64, 40) for step in (0, 29, 30, 99)] == [2, 2, 1, 1]
    assert factor(config, 0, 64, 32) == 2  # 16 px left on the shorter side: enough
    assert factor(config, 0, 64, 30) == 1  # 15: too few, drawn whole
    off = dataclasses.replace(config, coarse=CoarseConfig(until=0.0, min_side=1))
    assert factor(off, 0, 640, 480) == 1
    # A budget's re-plan moves the coarse phase with the rest of the schedule.
    repaced = schedules.repaced(config, 10, 200)
    # Its position is 10 + (step − 10) · 90/190, which passes 30 between steps 52 and 53.
    assert [factor(repaced, step, 64, 40) for step in (52, 53)] == [2, 1]


def test_a_coarse_view_is_the_whole_one_block_averaged_with_its_camera_scaled() -> None:
    whole = _batch(12, 8)
    coarse = whole.coarse(2)
    assert coarse.full is whole and coarse.index == whole.index and coarse.time == whole.time
    assert coarse.camera == whole.camera.scaled(0.5)
    assert (coarse.camera.width, coarse.camera.height) == (6, 4)
    blocks = whole.image.reshape(4, 2, 6, 2, 3).mean(dim=(1, 3))
    torch.testing.assert_close(coarse.image, blocks, rtol=0, atol=1e-7)
    assert whole.mask is not None and coarse.mask is not None
    torch.testing.assert_close(
        coarse.mask, whole.mask.reshape(4, 2, 6, 2, 1).mean(dim=(1, 3)), rtol=0, atol=1e-7
    )
    assert coarse.image.is_contiguous()
    assert whole.coarse(1) is whole
    assert _batch(12, 8, masked=False).coarse(2).mask is None


def test_a_coarse_view_of_sides_the_factor_does_not_divide_matches_its_camera() -> None:
    coarse = _batch(13, 9).coarse(2)
    assert coarse.image.shape == (coarse.camera.height, coarse.camera.width, 3)
    assert coarse.mask is not None and coarse.mask.shape[:2] == coarse.image.shape[:2]
    assert float(coarse.image.min()) >= 0.0 and float(coarse.image.max()) <= 1.0


def test_radii_are_counted_in_the_views_own_pixels() -> None:
    """`--densify.prune-screen-size` means the same on a coarse render: its radii count
    the whole view's pixels; the gradients are in NDC units already."""
    means2d = torch.zeros(3, 2, requires_grad=True)
    (means2d * torch.tensor([1.0, 2.0])).sum().backward()
    out = RenderOutput(
        rgb=torch.zeros(4, 4, 3),
        alpha=torch.zeros(4, 4, 1),
        depth=torch.zeros(4, 4, 1),
        means2d=means2d,
        radii=torch.tensor([[3, 2], [5, 5], [0, 0]]),
        visible=torch.tensor([True, True, False]),
        num_nonfinite=torch.zeros((), dtype=torch.long),
    )
    plain, scaled = view_statistics(out, 8, 6), view_statistics(out, 8, 6, pixel_scale=2.0)
    assert plain is not None and scaled is not None
    assert torch.equal(scaled.max_radius, 2 * plain.max_radius)
    assert torch.equal(scaled.grad_sum, plain.grad_sum)


def test_a_training_steps_radii_are_counted_in_its_whole_views_pixels(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path, max_iters=4, coarse=CoarseConfig(until=1.0, min_side=8))
    stats = trainer.train_step(0)
    assert stats.batch.full is not None
    coarse = densify_statistics(trainer.lifecycle, stats.out, stats.batch, None, 1)
    as_whole = densify_statistics(trainer.lifecycle, stats.out,
                                  dataclasses.replace(stats.batch, full=None), None, 1)  # fmt: skip
    assert coarse is not None and as_whole is not None
    assert float(as_whole.max_radius.max()) > 0
    assert torch.equal(coarse.max_radius, 2 * as_whole.max_radius)


def test_a_coarse_view_takes_the_whole_views_change_weights_shrunk(tmp_path: Path) -> None:
    config = tiny_config(data=str(demo_path(RIG)), losses=LossConfig(change_weight=4.0))
    trainer = Trainer(config, tmp_path, NullWriter())
    whole = trainer.data.next_train()
    full_weights = trainer.objective.pixel_weights(whole)
    coarse = whole.coarse(2)
    weights = trainer.objective.pixel_weights(coarse)
    assert full_weights is not None and weights is not None
    assert weights.shape == (*coarse.image.shape[:2], 1)
    assert torch.equal(weights, area_resize(full_weights, coarse.camera))
    assert float(weights.max()) > 1.0  # some changed pixels reach the coarse view


def test_a_run_draws_coarse_then_whole_and_says_so(tmp_path: Path) -> None:
    coarse = CoarseConfig(until=0.5, factor=2, min_side=8)
    trainer = tiny_trainer(tmp_path, max_iters=8, coarse=coarse)
    assert trainer.notes()[-1].startswith("[coarse] 12 of 12 training views are drawn at 1/2")
    shapes = [tuple(trainer.train_step(step).out.rgb.shape) for step in range(8)]
    assert shapes == [(16, 16, 3)] * 4 + [(32, 32, 3)] * 4
    assert all(torch.isfinite(p).all() for p in trainer.model.parameters())


def test_small_views_are_drawn_whole_and_the_run_says_why(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path, max_iters=4, coarse=CoarseConfig(until=1.0, min_side=32))
    assert "every training view is drawn whole" in trainer.notes()[-1]
    assert trainer.train_step(0).out.rgb.shape == (32, 32, 3)


def test_by_default_only_large_views_are_drawn_coarse() -> None:
    config, factor = tiny_config(max_iters=100), _factor
    assert (factor(config, 0, 480, 270), factor(config, 0, 128, 128)) == (2, 1)
    assert factor(config, 30, 480, 270) == 1  # the first 30 % only


def test_the_default_leaves_small_scenes_as_they_were_and_says_nothing(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path, max_iters=4)
    assert not any(note.startswith("[coarse]") for note in trainer.notes())
    assert trainer.train_step(0).batch.full is None
    off = tiny_trainer(tmp_path / "off", max_iters=4, coarse=CoarseConfig(until=0.0))
    assert not any(note.startswith("[coarse]") for note in off.notes())


@pytest.mark.parametrize(
    ("fields", "flag"),
    [({"until": 1.5}, "--coarse.until"), ({"factor": 0}, "--coarse.factor"),
     ({"min_side": 0}, "--coarse.min-side")],
)  # fmt: skip
def test_bad_coarse_settings_name_their_flag(fields: dict[str, float], flag: str) -> None:
    with pytest.raises(ConfigError, match=flag):
        CoarseConfig(**fields)  # type: ignore[arg-type]

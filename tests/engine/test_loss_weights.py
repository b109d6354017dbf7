"""Change-weighted photometric loss: on fixed cameras, pixels that show something that is
not usually there (a moving object) weigh 1 + `--losses.change-weight`."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch

from dyngs.config import LossConfig
from dyngs.datamanagers.procedural import ProceduralSceneConfig, demo_path
from dyngs.engine.trainer import Trainer, native_convolutions
from dyngs.engine.writer import NullWriter
from dyngs.losses.photometric import photometric
from tests.engine.helpers import tiny_config

RIG = ProceduralSceneConfig(resolution=48, num_times=9, fixed_cameras=4, num_test=2, num_val=0)


def _rig_trainer(tmp_path: Path, **losses: Any) -> Trainer:
    config = tiny_config(data=str(demo_path(RIG)), losses=LossConfig(**losses))
    return Trainer(config, tmp_path, NullWriter())


def test_changed_pixels_weigh_one_plus_the_change_weight(tmp_path: Path) -> None:
    trainer = _rig_trainer(tmp_path, change_weight=4.0)
    fixed = trainer.data.fixed_cameras
    assert fixed is not None
    heavy = 0
    for _ in range(len(trainer.scene.train)):
        batch = trainer.data.next_train()
        weights = trainer.objective.pixel_weights(batch)
        changed = fixed.changed(batch.index, batch.image, trainer.config.motion.pixel_change)
        assert weights is not None and changed is not None
        assert weights.shape == (*batch.image.shape[:2], 1)
        assert torch.equal(weights[..., 0], torch.where(changed, 5.0, 1.0))
        heavy += int(changed.sum())
    assert heavy > 0


def test_a_training_step_weighs_its_photometric_term(tmp_path: Path) -> None:
    """The step's photometric term is the weighted loss of its render, and differs from
    the unweighted one (so the weights did reach it)."""
    trainer = _rig_trainer(tmp_path, change_weight=4.0)
    stats = trainer.train_step(0)
    weights = trainer.objective.pixel_weights(stats.batch)
    assert weights is not None
    rgb, image, dssim = stats.out.rgb.detach(), stats.batch.image, trainer.config.losses.dssim
    with native_convolutions():  # as in the step, so the sums agree to the bit
        weighted, plain = photometric(rgb, image, dssim, weights), photometric(rgb, image, dssim)
    assert torch.equal(stats.terms["photometric"], weighted)
    assert not torch.equal(stats.terms["photometric"], plain)


def test_the_weights_multiply_the_datasets_mask(tmp_path: Path) -> None:
    trainer = _rig_trainer(tmp_path, change_weight=2.0, masked=True)
    batch = trainer.data.next_train()
    half = torch.full((*batch.image.shape[:2], 1), 0.5)
    weigh = trainer.objective.pixel_weights
    unmasked = weigh(dataclasses.replace(batch, mask=torch.ones_like(half)))
    weights = weigh(dataclasses.replace(batch, mask=half))
    assert unmasked is not None and weights is not None
    assert torch.equal(weights, unmasked * 0.5)


def test_without_a_change_weight_the_medians_are_never_read(tmp_path: Path) -> None:
    trainer = _rig_trainer(tmp_path, change_weight=0.0)
    batch = trainer.data.next_train()
    assert trainer.objective.pixel_weights(batch) is None
    trainer.train_step(0)
    assert "fixed_cameras" not in vars(trainer.data)  # cached_property: never computed


def test_moving_cameras_leave_the_loss_unweighted_and_the_run_says_so(tmp_path: Path) -> None:
    trainer = Trainer(tiny_config(losses=LossConfig(change_weight=4.0)), tmp_path, NullWriter())
    assert trainer.data.fixed_cameras is None
    assert trainer.objective.pixel_weights(trainer.data.next_train()) is None
    assert trainer.objective.change_weight_note().startswith(
        "warning: --losses.change-weight 4 has no effect"
    )


def test_a_rig_run_says_how_much_changed_pixels_count(tmp_path: Path) -> None:
    note = _rig_trainer(tmp_path, change_weight=4.0).objective.change_weight_note()
    assert note == (
        f"[loss] {RIG.fixed_cameras} fixed cameras: pixels that differ from their camera's "
        "temporal median count 5× in the photometric loss"
    )

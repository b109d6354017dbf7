"""Fixed cameras: which views share a camera, their temporal medians, and which pixels
show something that is not usually there."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from dyngs.datamanagers.datamanager import DataConfig, load_scene
from dyngs.datamanagers.fixed_cameras import FixedCameras, fixed_camera_groups
from dyngs.datamanagers.procedural import ProceduralSceneConfig, demo_path
from tests.engine.helpers import TINY_SCENE

RIG = ProceduralSceneConfig(resolution=48, num_times=9, fixed_cameras=4, num_test=2, num_val=0)


def _changed_by_hand(image: np.ndarray, median: np.ndarray, threshold: float) -> np.ndarray:
    """The definition, pixel by pixel: some channel differs from the median by more than
    the threshold at the pixel or at one of its eight neighbours."""
    height, width = image.shape[:2]
    raw = np.abs(image - median).max(axis=-1) > threshold
    out = np.zeros_like(raw)
    for y in range(height):
        for x in range(width):
            out[y, x] = raw[max(0, y - 1) : y + 2, max(0, x - 1) : x + 2].any()
    return out


def test_each_fixed_camera_has_its_views_in_time_order_and_their_median() -> None:
    scene = load_scene(str(demo_path(RIG)), DataConfig(), seed=0)
    split = scene.train
    fixed = FixedCameras.of(split)
    assert fixed is not None
    assert len(fixed.views) == len(fixed.cameras) == len(fixed.medians) == RIG.fixed_cameras
    assert sorted(i for views in fixed.views for i in views) == sorted(
        i for group in fixed_camera_groups(split) for i in group
    )
    for c, views in enumerate(fixed.views):
        times = [float(split.times[i]) for i in views]
        assert times == sorted(times) and len(set(times)) >= 3
        assert all(fixed.camera_of(i) == c for i in views)
        # The lower of the two middle values for an even count, as torch.median takes it.
        stack = np.sort(np.stack([split.images[i].numpy() for i in views]), axis=0)
        assert np.array_equal(fixed.medians[c].numpy(), stack[(len(views) - 1) // 2])


@pytest.mark.parametrize("threshold", [0.05, 0.1, 0.3])
def test_changed_pixels_are_the_definition(threshold: float) -> None:
    scene = load_scene(str(demo_path(RIG)), DataConfig(), seed=0)
    split = scene.train
    fixed = FixedCameras.of(split)
    assert fixed is not None
    seen = 0
    for c, views in enumerate(fixed.views):
        median = fixed.medians[c].numpy().astype(np.float32) / 255
        for i in views[:: max(1, len(views) // 3)]:
            image = split.images[i].float() / 255
            changed = fixed.changed(i, image, threshold)
            assert changed is not None and changed.dtype == torch.bool
            expected = _changed_by_hand(image.numpy(), median, threshold)
            assert np.array_equal(changed.numpy(), expected)
            seen += int(expected.sum())
    assert seen > 0  # the ball and the cube move in front of these cameras


def test_a_still_scene_changes_nowhere() -> None:
    scene = load_scene(str(demo_path(dataclasses.replace(RIG, motion=False))), DataConfig(), seed=0)
    fixed = FixedCameras.of(scene.train)
    assert fixed is not None
    for views in fixed.views:
        for i in views:
            changed = fixed.changed(i, scene.train.images[i].float() / 255, 0.1)
            assert changed is not None and not bool(changed.any())


def test_moving_cameras_have_no_fixed_cameras() -> None:
    scene = load_scene(str(demo_path(TINY_SCENE)), DataConfig(), seed=0)
    assert FixedCameras.of(scene.train) is None


def test_a_view_of_no_fixed_camera_has_no_change_map() -> None:
    scene = load_scene(str(demo_path(RIG)), DataConfig(), seed=0)
    fixed = FixedCameras.of(scene.train)
    assert fixed is not None
    outside = len(scene.train)
    assert fixed.camera_of(outside) is None
    assert fixed.changed(outside, torch.zeros(RIG.resolution, RIG.resolution, 3), 0.1) is None

"""The parser on the real scenes in ../shared/data (skipped when they are absent)."""

from __future__ import annotations

import math

import pytest
import torch

from dyngs.datamanagers.dnerf import parse_dnerf
from tests.datamanagers.fixtures import shared_scene


def _contains(box_lower: tuple[float, ...], box_upper: tuple[float, ...], half: float) -> bool:
    return all(lo < -half and hi > half for lo, hi in zip(box_lower, box_upper, strict=True))


def test_lego_tiny() -> None:
    scene = parse_dnerf(shared_scene("lego-tiny"), background=(0.0, 0.0, 0.0))
    assert (len(scene.train), len(scene.val), len(scene.test)) == (50, 11, 20)
    assert scene.train.masks is None  # RGB on black, no alpha
    assert tuple(scene.train.images[0].shape) == (100, 100, 3)
    camera = scene.train.cameras[0]
    assert camera.fx == pytest.approx(0.5 * 100 / math.tan(0.5 * 0.6911112070083618), rel=1e-6)
    assert float(scene.train.times.min()) == 0.0 and float(scene.train.times.max()) == 1.0
    # The lego sits around the origin, inside roughly ±1.2; cameras are ~4 away.
    assert _contains(scene.scene_box.lower, scene.scene_box.upper, 1.2)
    assert max(scene.scene_box.size) < 5.0
    # Every camera looks at the origin: it projects near the image centre.
    for cam in scene.train.cameras:
        origin = cam.world_to_camera[:3, 3]
        u = cam.fx * origin[0] / origin[2] + cam.cx
        v = cam.fy * origin[1] / origin[2] + cam.cy
        assert origin[2] > 0 and abs(u - 50) < 15 and abs(v - 50) < 15


def test_mujoco_collision_downscaled() -> None:
    scene = parse_dnerf(shared_scene("mujoco-collision"), downscale=8)
    # The data README says 23 / 23 for val / test; the JSON files hold 21 each.
    assert (len(scene.train), len(scene.val), len(scene.test)) == (108, 21, 21)
    assert tuple(scene.train.images[0].shape) == (100, 100, 3)
    assert scene.train.cameras[0].fx == pytest.approx(857.8027682038233 / 8)
    assert scene.train.masks is not None
    assert 0.2 < float(torch.stack(list(scene.train.masks)).float().mean()) / 255 < 0.9
    assert tuple(scene.points.shape) == (100_000, 3) and scene.point_colors is not None
    assert _contains(scene.scene_box.lower, scene.scene_box.upper, 1.0)

"""The browser's camera and dyngs's describe the same view: conversions both ways."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dyngs.tools.render import look_at
from dyngs.types import Camera
from dyngs.viewer.camera import (
    BrowserPose,
    camera_of,
    frame_size,
    look_distance,
    matrix_to_quaternion,
    pose_of,
    quaternion_to_matrix,
)


def _random_rotations(count: int) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    rotations = []
    for _ in range(count):
        q, r = np.linalg.qr(rng.normal(size=(3, 3)))
        q = q * np.sign(np.diag(r))
        rotations.append(q if np.linalg.det(q) > 0 else -q)
    # The branches of the quaternion extraction: half turns about each axis, identity.
    rotations += [np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1]), np.eye(3)]
    return rotations


@pytest.mark.parametrize("rotation", _random_rotations(20))
def test_quaternion_round_trip(rotation: np.ndarray) -> None:
    q = matrix_to_quaternion(rotation)
    assert np.isclose(np.linalg.norm(q), 1.0) and q[0] >= 0
    assert np.allclose(quaternion_to_matrix(q), rotation, atol=1e-12)


def test_quaternion_of_a_quarter_turn_about_z() -> None:
    # Hand-computed: 90° about z is (cos 45°, 0, 0, sin 45°); it takes x to y.
    q = np.array([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])
    assert np.allclose(quaternion_to_matrix(q) @ [1.0, 0, 0], [0.0, 1, 0])
    assert np.allclose(matrix_to_quaternion(quaternion_to_matrix(q)), q)


def _camera(width: int = 64, height: int = 48) -> Camera:
    w2c = look_at(np.array([3.0, -2.0, 1.5]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    focal = 0.5 * height / math.tan(math.radians(25))
    return Camera(
        focal,
        focal,
        width / 2,
        height / 2,
        torch.from_numpy(w2c),
        width,
        height,
        near=0.05,
        far=50.0,
    )


def test_a_camera_comes_back_from_its_browser_pose() -> None:
    camera = _camera()
    pose = pose_of(camera)
    assert math.isclose(pose.fov_y, math.radians(50))
    assert np.allclose(pose.position, [3.0, -2.0, 1.5])
    back = camera_of(pose, camera.width, camera.height, like=camera)
    assert torch.allclose(back.world_to_camera, camera.world_to_camera, atol=1e-12)
    assert (back.fx, back.fy, back.cx, back.cy) == pytest.approx(
        (camera.fx, camera.fy, camera.cx, camera.cy)
    )
    assert (back.near, back.far) == (0.05, 50.0)


def test_a_larger_frame_scales_the_focal_length_with_the_height() -> None:
    camera = _camera()
    back = camera_of(pose_of(camera), 640, 480, like=camera)
    assert back.fy == pytest.approx(camera.fy * 10) and back.fx == back.fy
    assert (back.cx, back.cy) == (320, 240)


def test_the_browser_pose_is_opencv() -> None:
    # The camera's +z (forward) must point from its centre to what it looks at.
    pose = pose_of(_camera())
    forward = quaternion_to_matrix(pose.wxyz)[:, 2]
    assert np.allclose(forward, -pose.position / np.linalg.norm(pose.position))
    assert look_distance(pose, np.zeros(3)) == pytest.approx(np.linalg.norm(pose.position))
    behind = BrowserPose(pose.wxyz, pose.position, pose.fov_y)
    assert look_distance(behind, 2 * pose.position) == pytest.approx(1e-3)


@pytest.mark.parametrize(
    ("aspect", "side", "size"), [(4 / 3, 800, (800, 600)), (0.5, 400, (200, 400)), (1.0, 7, (7, 7))]
)
def test_frame_size_keeps_the_aspect(aspect: float, side: int, size: tuple[int, int]) -> None:
    assert frame_size(aspect, side) == size

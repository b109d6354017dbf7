"""Cameras between the browser and dyngs.

The browser (viser) describes its camera as a pose `P_world = R p_camera + t`, with R a
quaternion (w, x, y, z), in the OpenCV convention (x right, y down, z forward, the same
as dyngs), a vertical field of view in radians and the canvas's size. dyngs draws with a
world-to-camera matrix and pixel intrinsics (`dyngs.types.Camera`). These functions turn
one into the other, both ways, with numpy only, so they are tested without a browser.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch
from jaxtyping import Float

from dyngs.types import Camera


@dataclass(frozen=True)
class BrowserPose:
    """A camera as the browser holds it: orientation, position, vertical field of view."""

    wxyz: Float[np.ndarray, " 4"]
    """Rotation camera → world as a unit quaternion (w, x, y, z)."""
    position: Float[np.ndarray, " 3"]
    """Camera centre in world space."""
    fov_y: float
    """Vertical field of view in radians."""


def quaternion_to_matrix(wxyz: Float[np.ndarray, " 4"]) -> Float[np.ndarray, "3 3"]:
    """The rotation matrix of a quaternion (w, x, y, z); it need not be normalised."""
    w, x, y, z = np.asarray(wxyz, dtype=np.float64) / np.linalg.norm(wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion(rotation: Float[np.ndarray, "3 3"]) -> Float[np.ndarray, " 4"]:
    """The unit quaternion (w, x, y, z, with w ≥ 0) of a rotation matrix, from its largest
    diagonal combination so that no branch divides by a small number (Shepperd 1978)."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = np.trace(m)
    candidates = [trace, m[0, 0], m[1, 1], m[2, 2]]
    k = int(np.argmax(candidates))
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = [s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i, j, n = k - 1, k % 3, (k + 1) % 3
        s = 2.0 * math.sqrt(max(1.0 + m[i, i] - m[j, j] - m[n, n], 1e-300))
        q = [0.0] * 4
        q[0] = (m[n, j] - m[j, n]) / s
        q[1 + i] = s / 4
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + n] = (m[n, i] + m[i, n]) / s
    quat = np.array(q)
    quat /= np.linalg.norm(quat)
    return quat if quat[0] >= 0 else -quat


def pose_of(camera: Camera) -> BrowserPose:
    """Where the browser must stand to see what `camera` sees (its principal point is
    taken to be the image centre, as the browser's always is)."""
    w2c = camera.world_to_camera.detach().double().cpu().numpy()
    camera_to_world = w2c[:3, :3].T
    position = -camera_to_world @ w2c[:3, 3]
    fov_y = 2.0 * math.atan(0.5 * camera.height / camera.fy)
    return BrowserPose(matrix_to_quaternion(camera_to_world), position, fov_y)


def frame_size(aspect: float, long_side: int) -> tuple[int, int]:
    """(width, height) of a frame of this aspect ratio (width / height) whose longer side
    is `long_side` pixels."""
    if aspect >= 1.0:
        return long_side, max(1, round(long_side / aspect))
    return max(1, round(long_side * aspect)), long_side


def camera_of(pose: BrowserPose, width: int, height: int, like: Camera) -> Camera:
    """The dyngs camera that draws the browser's view into a width × height frame: square
    pixels, centred principal point, near and far planes taken from `like` (a camera of
    the scene, whose planes suit its scale)."""
    rotation = quaternion_to_matrix(pose.wxyz).T  # world → camera
    w2c = np.eye(4)
    w2c[:3, :3] = rotation
    w2c[:3, 3] = -rotation @ np.asarray(pose.position, dtype=np.float64)
    focal = 0.5 * height / math.tan(0.5 * pose.fov_y)
    matrix = torch.from_numpy(w2c).to(like.world_to_camera)
    return dataclasses.replace(
        like, fx=focal, fy=focal, cx=width / 2, cy=height / 2,
        world_to_camera=matrix, width=width, height=height,
    )  # fmt: skip


def look_distance(pose: BrowserPose, target: Float[np.ndarray, " 3"]) -> float:
    """How far along the view direction the point nearest `target` lies (the orbit
    centre the mouse turns around); at least a small positive distance."""
    forward = quaternion_to_matrix(pose.wxyz)[:, 2]
    return max(float((np.asarray(target) - pose.position) @ forward), 1e-3)

"""Camera-pose helpers every parser shares: Blender → OpenCV conversion, rigid-transform
checks, the scene box that cameras (and a point cloud) imply, random initial points.

Letters: F cameras, P points.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from dyngs.types import Camera, SceneBox

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Flips the camera's y and z axes: OpenGL/Blender (y up, looks down −z) ↔ OpenCV."""

ORTHONORMAL_TOLERANCE = 1e-3
"""Largest |RᵀR − I| entry accepted for a camera rotation (float32 JSON rounding is ~1e-7)."""


def check_rigid(matrix: object) -> Float[np.ndarray, "4 4"] | str:
    """The matrix as float64 4×4 if it is a rigid transform, else a short problem statement.

    Rejected: not 4×4 numbers, non-finite entries, a last row other than (0, 0, 0, 1), a
    singular or non-orthonormal (scaled, sheared) rotation block, a reflection.
    """
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        return "transform_matrix is not a 4×4 matrix of numbers"
    if m.shape != (4, 4):
        return f"transform_matrix has shape {m.shape}, need 4×4"
    if not np.isfinite(m).all():
        return "transform_matrix has non-finite entries"
    if np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-6:
        return f"transform_matrix last row is {m[3].tolist()}, need [0, 0, 0, 1]"
    rotation = m[:3, :3]
    det = float(np.linalg.det(rotation))
    if abs(det) < 1e-6:
        return f"transform_matrix rotation is singular (det {det:.3g})"
    error = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if error > ORTHONORMAL_TOLERANCE:
        return f"transform_matrix rotation is not orthonormal (|RᵀR − I| = {error:.3g})"
    if det < 0:
        return "transform_matrix rotation is a reflection (det −1)"
    return m


def blender_to_world_to_camera(c2w_gl: Float[np.ndarray, "4 4"]) -> Float[np.ndarray, "4 4"]:
    """OpenCV world-to-camera from a Blender/OpenGL camera-to-world (rigid) matrix."""
    c2w_cv = c2w_gl @ GL_TO_CV
    rotation, center = c2w_cv[:3, :3], c2w_cv[:3, 3]
    w2c = np.eye(4)
    w2c[:3, :3] = rotation.T
    w2c[:3, 3] = -rotation.T @ center
    return w2c


def world_to_camera_to_blender(w2c: Float[np.ndarray, "4 4"]) -> Float[np.ndarray, "4 4"]:
    """The inverse of `blender_to_world_to_camera` (used to write D-NeRF datasets)."""
    rotation, translation = w2c[:3, :3], w2c[:3, 3]
    c2w_cv = np.eye(4)
    c2w_cv[:3, :3] = rotation.T
    c2w_cv[:3, 3] = -rotation.T @ translation
    return c2w_cv @ GL_TO_CV


def scene_box_from_cameras(
    cameras: list[Camera],
    points: Float[Tensor, "P 3"] | None = None,
    margin: float = 1.1,
) -> SceneBox:
    """A cube around what the cameras look at, grown to hold most of a point cloud.

    Centre c: the least-squares point closest to every camera's optical axis, i.e. the
    solution of Σᵢ (I − dᵢdᵢᵀ)(c − oᵢ) = 0 for camera centres oᵢ and unit view directions
    dᵢ. When the axes are (nearly) parallel that system is singular along them, so a
    tiny ridge term pulls c towards the point one mean camera distance ahead of the mean
    camera.

    Half-size h: the median over cameras of ‖oᵢ − c‖ · tan(½ horizontal fov) · `margin`,
    i.e. the half-width each camera sees in the plane through c, so the cube is roughly
    what every camera sees around the centre.

    With a point cloud the box becomes the union of the cube and the points' 1st–99th
    percentile bounds per axis (percentiles so a few stray SfM points do not blow it up).
    """
    if not cameras:
        raise ValueError("scene_box_from_cameras needs at least one camera")
    origins = np.stack([cam.center.double().cpu().numpy() for cam in cameras])
    # The camera's +z axis in world space is the third row of the world-to-camera rotation.
    directions = np.stack([cam.rotation[2].double().cpu().numpy() for cam in cameras])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    projectors = np.eye(3) - directions[:, :, None] * directions[:, None, :]
    lhs = projectors.sum(0)
    rhs = np.einsum("fij,fj->i", projectors, origins)
    spread = float(np.linalg.norm(origins - origins.mean(0), axis=1).mean())
    fallback = origins.mean(0) + directions.mean(0) * max(spread, 1.0)
    ridge = 1e-6 * float(np.trace(lhs))
    center = np.linalg.solve(lhs + ridge * np.eye(3), rhs + ridge * fallback)

    tan_half_fov = np.array([0.5 * cam.width / cam.fx for cam in cameras])
    distances = np.linalg.norm(origins - center, axis=1)
    half = float(np.median(distances * tan_half_fov)) * margin
    if not math.isfinite(half) or half <= 0:
        half = 1.0
    lower, upper = center - half, center + half
    if points is not None and len(points) > 0:
        pts = points.double().cpu().numpy()
        lower = np.minimum(lower, np.percentile(pts, 1, axis=0))
        upper = np.maximum(upper, np.percentile(pts, 99, axis=0))
    return SceneBox(
        (float(lower[0]), float(lower[1]), float(lower[2])),
        (float(upper[0]), float(upper[1]), float(upper[2])),
    )


def random_points_in_box(box: SceneBox, count: int, seed: int) -> Float[Tensor, "P 3"]:
    """`count` points uniform in the box, from a generator seeded with `seed`."""
    generator = torch.Generator().manual_seed(seed)
    unit = torch.rand(count, 3, generator=generator, dtype=torch.float64)
    lower = torch.tensor(box.lower, dtype=torch.float64)
    upper = torch.tensor(box.upper, dtype=torch.float64)
    return (lower + unit * (upper - lower)).float()

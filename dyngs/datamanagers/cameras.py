"""Camera-pose helpers every parser shares: Blender → OpenCV conversion, rigid-transform
checks, the scene box that cameras (and a point cloud) imply, random initial points.

Letters: F cameras, P points.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from jaxtyping import Float, Int
from torch import Tensor

from dyngs.types import Camera, SceneBox

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Flips the camera's y and z axes: OpenGL/Blender (y up, looks down −z) ↔ OpenCV."""

ORTHONORMAL_TOLERANCE = 1e-3
"""Largest |RᵀR − I| entry accepted for a camera rotation (float32 JSON rounding is ~1e-7)."""


def check_rigid(
    matrix: object, name: str = "transform_matrix", allow_reflection: bool = False
) -> Float[np.ndarray, "4 4"] | str:
    """The matrix as float64 4×4 if it is a rigid transform, else a short problem statement.

    Rejected: not 4×4 numbers, non-finite entries, a last row other than (0, 0, 0, 1), a
    singular or non-orthonormal (scaled, sheared) rotation block, a reflection (unless
    `allow_reflection`: a capture whose world frame is mirrored, see `mirror_world`).
    """
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        return f"{name} is not a 4×4 matrix of numbers"
    if m.shape != (4, 4):
        return f"{name} has shape {m.shape}, need 4×4"
    if not np.isfinite(m).all():
        return f"{name} has non-finite entries"
    if np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-6:
        return f"{name} last row is {m[3].tolist()}, need [0, 0, 0, 1]"
    rotation = m[:3, :3]
    det = float(np.linalg.det(rotation))
    if abs(det) < 1e-6:
        return f"{name} rotation is singular (det {det:.3g})"
    error = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if error > ORTHONORMAL_TOLERANCE:
        return f"{name} rotation is not orthonormal (|RᵀR − I| = {error:.3g})"
    if det < 0 and not allow_reflection:
        return f"{name} rotation is a reflection (det −1)"
    return m


MIRROR_X = np.diag([-1.0, 1.0, 1.0, 1.0])
"""Mirrors the world in x: x_world → −x_world."""


def mirror_world(w2c: Float[np.ndarray, "4 4"]) -> Float[np.ndarray, "4 4"]:
    """The world-to-camera matrix of the same camera in a world mirrored in x. A capture
    whose every camera is a reflection (det −1) has a left-handed world frame; mirrored,
    every camera becomes a rotation and the pictures are unchanged."""
    return w2c @ MIRROR_X


def blender_to_world_to_camera(c2w_gl: Float[np.ndarray, "4 4"]) -> Float[np.ndarray, "4 4"]:
    """OpenCV world-to-camera from a Blender/OpenGL camera-to-world (rigid) matrix."""
    c2w_cv = c2w_gl @ GL_TO_CV
    rotation, center = c2w_cv[:3, :3], c2w_cv[:3, 3]
    w2c = np.eye(4)
    w2c[:3, :3] = rotation.T
    w2c[:3, 3] = -rotation.T @ center
    return w2c


LLFF_TO_CV = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
"""Reorders LLFF camera axes (down, right, back) into OpenCV's (right, down, forward)."""


def llff_to_world_to_camera(pose: Float[np.ndarray, "3 4"]) -> Float[np.ndarray, "4 4"]:
    """OpenCV world-to-camera from an LLFF camera-to-world [down | right | back | centre].

    The three rotation columns are the camera's down, right and backward axes in world
    space: OpenCV's x (right) is LLFF's second column, y (down) its first and z (forward)
    the negated third.
    """
    rotation = pose[:, :3] @ LLFF_TO_CV
    return rotation_center_to_world_to_camera(rotation.T, pose[:, 3])


def rotation_center_to_world_to_camera(
    rotation: Float[np.ndarray, "3 3"], center: Float[np.ndarray, " 3"]
) -> Float[np.ndarray, "4 4"]:
    """World-to-camera from its rotation (rows: the camera axes in world space) and the
    camera centre: x_cam = R (x − c), so t = −R c."""
    w2c = np.eye(4)
    w2c[:3, :3] = rotation
    w2c[:3, 3] = -rotation @ center
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


def _distinct(cameras: list[Camera], ranges: list[tuple[float, float]]) -> list[int]:
    """Indices of the first camera of each distinct (pose, intrinsics, size, depth range)."""
    seen: dict[tuple[float, ...], int] = {}
    for index, (camera, depth) in enumerate(zip(cameras, ranges, strict=True)):
        pose = camera.world_to_camera.double().flatten().tolist()
        key = (*pose, camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)
        seen.setdefault(tuple(round(v, 6) for v in (*key, *depth)), index)
    return sorted(seen.values())


def points_in_common_view(
    cameras: list[Camera],
    depth_ranges: list[tuple[float, float]],
    count: int,
    seed: int,
    max_cameras: int = 64,
    rounds: int = 32,
) -> Float[Tensor, "P 3"]:
    """`count` points spread uniformly over the volume that every camera sees.

    Camera j sees a point when it projects inside the image with a depth in
    `depth_ranges[j]` (near, far). Candidates are drawn in the frustum of a random camera
    (a random pixel and a depth with density ∝ depth², i.e. uniform in the frustum's
    volume) and kept when every camera sees them: each frustum holds the common volume
    at a constant density, so the kept points are uniform in it. Repeated cameras count
    once, and at most `max_cameras` evenly spread ones are checked (the acceptance test
    costs one projection per camera). If the cameras share too little view for `count`
    points to pass in `rounds` batches, the rest are the candidates most cameras see.
    """
    if count < 1:
        raise ValueError(f"count must be ≥ 1, got {count}")
    if len(cameras) != len(depth_ranges) or not cameras:
        raise ValueError("points_in_common_view needs one depth range per camera, and a camera")
    chosen = _distinct(cameras, depth_ranges)
    if len(chosen) > max_cameras:
        chosen = [chosen[round(i)] for i in np.linspace(0, len(chosen) - 1, max_cameras)]
    cams = [cameras[i] for i in chosen]
    near = np.array([max(depth_ranges[i][0], cameras[i].near) for i in chosen])
    far = np.array([depth_ranges[i][1] for i in chosen])
    if not (np.isfinite(near).all() and np.isfinite(far).all() and (far > near).all()):
        raise ValueError("every depth range needs finite near < far")
    w2c = np.stack([c.world_to_camera.double().cpu().numpy() for c in cams])
    rotations, translations = w2c[:, :3, :3], w2c[:, :3, 3]
    intrinsics = np.array([(c.fx, c.fy, c.cx, c.cy, c.width, c.height) for c in cams])
    rng = np.random.default_rng(seed)
    batch = max(1024, 2 * count)
    accepted: list[np.ndarray] = []
    num_accepted = 0
    spare = np.zeros((0, 3))
    spare_score = np.zeros(0, dtype=np.int64)
    for _ in range(rounds):
        source = rng.integers(0, len(cams), size=batch)
        world = _in_frustums(rng, source, rotations, translations, intrinsics, near, far)
        score = _visibility(world, rotations, translations, intrinsics, near, far)
        full = score == len(cams)
        accepted.append(world[full])
        num_accepted += int(full.sum())
        if num_accepted >= count:
            break
        spare = np.concatenate([spare, world[~full]])
        spare_score = np.concatenate([spare_score, score[~full]])
        if len(spare) > count:
            best = np.argpartition(-spare_score, count)[:count]
            spare, spare_score = spare[best], spare_score[best]
    points = np.concatenate(accepted)[:count]
    if len(points) < count:
        order = np.argsort(-spare_score, kind="stable")[: count - len(points)]
        points = np.concatenate([points, spare[order]])
    return torch.from_numpy(points).float()


def _in_frustums(
    rng: np.random.Generator,
    source: Int[np.ndarray, " B"],
    rotations: Float[np.ndarray, "C 3 3"],
    translations: Float[np.ndarray, "C 3"],
    intrinsics: Float[np.ndarray, "C 6"],
    near: Float[np.ndarray, " C"],
    far: Float[np.ndarray, " C"],
) -> Float[np.ndarray, "B 3"]:
    """One world point uniform in the frustum of camera `source[i]` for each i: a random
    pixel, and a depth with density ∝ depth² between its near and far."""
    batch = len(source)
    fx, fy, cx, cy, width, height = intrinsics[source].T
    u = rng.uniform(0.0, 1.0, size=batch) * width
    v = rng.uniform(0.0, 1.0, size=batch) * height
    a3, b3 = near[source] ** 3, far[source] ** 3
    depth = np.cbrt(a3 + rng.uniform(0.0, 1.0, size=batch) * (b3 - a3))
    local = np.stack([(u - cx) / fx * depth, (v - cy) / fy * depth, depth], axis=1)
    # x_world = Rᵀ (x_cam − t), one candidate per row.
    return np.einsum("nji,nj->ni", rotations[source], local - translations[source])


def _visibility(
    points: Float[np.ndarray, "P 3"],
    rotations: Float[np.ndarray, "F 3 3"],
    translations: Float[np.ndarray, "F 3"],
    intrinsics: Float[np.ndarray, "F 6"],
    near: Float[np.ndarray, " F"],
    far: Float[np.ndarray, " F"],
    chunk: int = 8192,
) -> np.ndarray:
    """How many of the cameras see each point (in the image, depth within near..far)."""
    score = np.zeros(len(points), dtype=np.int64)
    fx, fy, cx, cy, width, height = (column[:, None] for column in intrinsics.T)
    for start in range(0, len(points), chunk):
        block = points[start : start + chunk]
        local = np.einsum("fij,pj->fpi", rotations, block) + translations[:, None, :]
        z = local[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = fx * local[..., 0] / z + cx
            v = fy * local[..., 1] / z + cy
        inside = (z >= near[:, None]) & (z <= far[:, None])
        inside &= (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
        score[start : start + chunk] = inside.sum(0)
    return score


def depth_ranges_around_box(cameras: list[Camera], box: SceneBox) -> list[tuple[float, float]]:
    """Per camera, the depths (along its optical axis) that the box's bounding sphere spans:
    the near/far bounds of formats that give none."""
    center = np.asarray(box.center)
    radius = 0.5 * box.diagonal
    ranges: list[tuple[float, float]] = []
    for camera in cameras:
        w2c = camera.world_to_camera.double().cpu().numpy()
        depth = float(w2c[2, :3] @ center + w2c[2, 3])
        near = max(depth - radius, camera.near)
        ranges.append((near, max(depth + radius, 2.0 * near)))
    return ranges


def share_ahead(world_to_cameras: list[Float[np.ndarray, "4 4"]]) -> float:
    """The share of distinct cameras that have in front of them the point closest to all
    their optical axes (in the least-squares sense): 1 for a rig that looks at one scene.
    A rig whose matrices are read the wrong way round (camera-to-world given as
    world-to-camera) looks away from itself and scores near 0. Cameras whose axes are
    nearly parallel have no such point; they score 1."""
    seen: dict[tuple[float, ...], Float[np.ndarray, "4 4"]] = {}
    for w2c in world_to_cameras:
        seen.setdefault(tuple(np.round(w2c[:3].ravel(), 4)), w2c)
    if len(seen) < 2:
        return 1.0
    rotations = np.stack([m[:3, :3] for m in seen.values()])
    inverses = np.linalg.inv(rotations)
    centres = -np.einsum("cij,cj->ci", inverses, np.stack([m[:3, 3] for m in seen.values()]))
    axes = inverses[:, :, 2]  # the camera's +z in world space
    axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    projectors = np.eye(3) - axes[:, :, None] * axes[:, None, :]
    lhs = projectors.sum(0)
    if np.linalg.cond(lhs) > 1e6:
        return 1.0
    point = np.linalg.solve(lhs, np.einsum("cij,cj->i", projectors, centres))
    depth = np.einsum("ci,ci->c", point - centres, axes)
    return float((depth > 0).mean())

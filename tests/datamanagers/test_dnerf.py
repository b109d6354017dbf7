"""The D-NeRF parser on tiny fixtures built from known cameras."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from dyngs.datamanagers.dnerf import parse_dnerf
from dyngs.ply import write_ply
from dyngs.types import Camera
from tests.datamanagers.fixtures import FrameSpec, random_c2w, small_dataset, write_dataset


def project(camera: Camera, points: np.ndarray) -> np.ndarray:
    """Pixel coordinates (u, v) of world points through an OpenCV camera."""
    w2c = camera.world_to_camera.double().numpy()
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    assert (cam[:, 2] > 0).all()
    return np.stack(
        [
            camera.fx * cam[:, 0] / cam[:, 2] + camera.cx,
            camera.fy * cam[:, 1] / cam[:, 2] + camera.cy,
        ],
        axis=1,
    )


def blender_points_and_pixels(
    rng: np.random.Generator, fx: float, fy: float, cx: float, cy: float
) -> tuple[np.ndarray, np.ndarray]:
    """Points in a Blender camera's frame (in front = −z, y up) and where they must land."""
    depth = rng.uniform(1.0, 5.0, size=20)
    x, y = rng.uniform(-0.5, 0.5, size=(2, 20)) * depth
    local = np.stack([x, y, -depth], axis=1)
    # Straight from the convention: right is +u, up is −v.
    pixels = np.stack([cx + fx * x / depth, cy - fy * y / depth], axis=1)
    return local, pixels


@pytest.mark.parametrize("intrinsics", ["camera_angle_x", "per-frame", "top-level"])
def test_cameras_project_known_points_to_expected_pixels(tmp_path: Path, intrinsics: str) -> None:
    rng = np.random.default_rng(1)
    width, height = 12, 10
    if intrinsics == "camera_angle_x":
        angle = math.radians(55)
        fx = fy = 0.5 * width / math.tan(0.5 * angle)
        cx, cy = width / 2, height / 2
        top: dict[str, object] = {"camera_angle_x": angle}
        extra: dict[str, object] = {}
    else:
        fx, fy, cx, cy = 11.5, 13.0, 5.25, 4.75
        k: dict[str, object] = {"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": width, "h": height}
        top, extra = ({}, k) if intrinsics == "per-frame" else (k, {})
    frames = [
        FrameSpec(random_c2w(rng), t, np.zeros((height, width, 3), np.uint8), extra)
        for t in (0.0, 0.25, 1.0)
    ]
    folder = write_dataset(tmp_path / "scene", {"train": frames, "test": frames[:1]}, top)
    scene = parse_dnerf(folder)

    assert scene.train.times.tolist() == [0.0, 0.25, 1.0]
    assert len(scene.val) == len(scene.test) == 1  # no val file: the test split stands in
    for frame, camera in zip(frames, scene.train.cameras, strict=True):
        assert (camera.width, camera.height) == (width, height)
        assert camera.fx == pytest.approx(fx) and camera.fy == pytest.approx(fy)
        assert (camera.cx, camera.cy) == (pytest.approx(cx), pytest.approx(cy))
        local, expected = blender_points_and_pixels(rng, fx, fy, cx, cy)
        world = local @ frame.c2w[:3, :3].T + frame.c2w[:3, 3]
        np.testing.assert_allclose(project(camera, world), expected, atol=0.5)
        np.testing.assert_allclose(camera.center.double().numpy(), frame.c2w[:3, 3], atol=1e-5)


def test_downscale_halves_sizes_and_intrinsics(tmp_path: Path) -> None:
    folder = small_dataset(tmp_path / "scene", width=8, height=6)
    full, half = parse_dnerf(folder), parse_dnerf(folder, downscale=2)
    for a, b, image in zip(full.train.cameras, half.train.cameras, half.train.images, strict=True):
        assert (b.width, b.height) == (4, 3) and tuple(image.shape) == (3, 4, 3)
        assert (b.fx, b.fy, b.cx, b.cy) == pytest.approx((a.fx / 2, a.fy / 2, a.cx / 2, a.cy / 2))
        torch.testing.assert_close(a.world_to_camera, b.world_to_camera)
    assert half.train.masks is not None and tuple(half.train.masks[0].shape) == (3, 4, 1)


def test_rgba_is_composited_over_the_background_and_alpha_becomes_the_mask(
    tmp_path: Path,
) -> None:
    rng = np.random.default_rng(2)
    image = np.zeros((4, 4, 4), np.uint8)
    image[0, 0] = (200, 100, 50, 128)
    image[1, 1] = (10, 20, 30, 255)
    frames = [FrameSpec(random_c2w(rng), 0.5, image)]
    folder = write_dataset(tmp_path / "scene", {"train": frames, "test": frames})
    scene = parse_dnerf(folder, background=(0.2, 0.4, 0.6))
    rgb = scene.train.images[0]
    assert rgb.dtype == torch.uint8 and tuple(rgb.shape) == (4, 4, 3)
    # 200·128/255 + 0.2·255·(1 − 128/255) = 100.39 + 25.4 = 125.79 → 126 (and so on).
    assert rgb[0, 0].tolist() == [126, 101, 101]
    assert rgb[1, 1].tolist() == [10, 20, 30]
    assert rgb[2, 2].tolist() == [51, 102, 153]
    assert scene.train.masks is not None
    assert scene.train.masks[0][0, 0, 0] == 128 and scene.train.masks[0][2, 2, 0] == 0
    assert scene.background.tolist() == pytest.approx([0.2, 0.4, 0.6])


def test_rgb_images_have_no_mask_and_random_points_fill_the_box(tmp_path: Path) -> None:
    folder = small_dataset(tmp_path / "scene", alpha=False)
    scene = parse_dnerf(folder, num_random_points=500, seed=3)
    assert scene.train.masks is None and scene.point_colors is None
    assert tuple(scene.points.shape) == (500, 3)
    lower, upper = torch.tensor(scene.scene_box.lower), torch.tensor(scene.scene_box.upper)
    assert ((scene.points >= lower - 1e-5) & (scene.points <= upper + 1e-5)).all()
    torch.testing.assert_close(
        parse_dnerf(folder, num_random_points=500, seed=3).points, scene.points
    )
    assert not torch.equal(parse_dnerf(folder, num_random_points=500, seed=4).points, scene.points)
    assert scene.train.paths is not None and scene.train.paths[0].name == "r_000.png"


def test_point_cloud_is_used_and_widens_the_box(tmp_path: Path) -> None:
    folder = small_dataset(tmp_path / "scene")
    camera_box = parse_dnerf(folder).scene_box
    rng = np.random.default_rng(4)
    xyz = rng.uniform(-30, 30, size=(1000, 3))
    color = rng.integers(0, 256, size=(1000, 3)).astype(np.uint8)
    write_ply(
        folder / "points3d.ply",
        {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
        | {c: color[:, i] for i, c in enumerate(("red", "green", "blue"))},
    )
    scene = parse_dnerf(folder)
    assert tuple(scene.points.shape) == (1000, 3) and scene.point_colors is not None
    np.testing.assert_allclose(scene.point_colors.numpy(), color / 255.0, atol=1e-6)
    assert scene.scene_box.lower[0] < camera_box.lower[0] - 20
    assert scene.scene_box.upper[2] > camera_box.upper[2] + 20


def test_scene_box_centres_on_what_the_cameras_look_at(tmp_path: Path) -> None:
    """Cameras on a sphere of radius 4 around (1, 2, 3), all looking at it."""
    rng = np.random.default_rng(5)
    target = np.array([1.0, 2.0, 3.0])
    frames = []
    for _ in range(8):
        c2w = random_c2w(rng)
        c2w[:3, 3] = target + 4.0 * c2w[:3, 2]
        frames.append(FrameSpec(c2w, 0.0, np.zeros((10, 10, 3), np.uint8)))
    folder = write_dataset(tmp_path / "scene", {"train": frames, "test": frames[:1]})
    box = parse_dnerf(folder, num_random_points=10).scene_box
    np.testing.assert_allclose(box.center, target, atol=1e-4)
    # half-size = distance · tan(½ fov) · 1.1 with fov = 50°
    assert box.size[0] / 2 == pytest.approx(4.0 * math.tan(math.radians(25)) * 1.1, rel=1e-4)

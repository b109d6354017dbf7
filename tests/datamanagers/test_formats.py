"""Panoptic, DyNeRF and Nerfies captures rendered from the procedural scene parse back to
the cameras, times and images they were made from."""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import torch

from dyngs.datamanagers import dynerf
from dyngs.datamanagers.base import SceneData, Split
from dyngs.datamanagers.datamanager import DataConfig, load_scene
from dyngs.datamanagers.dynerf import parse_dynerf
from dyngs.datamanagers.nerfies import parse_nerfies
from dyngs.datamanagers.panoptic import parse_panoptic
from dyngs.errors import ConfigError, DatasetError
from dyngs.types import Camera
from tests.datamanagers.formats import (
    NerfiesWorld,
    Truth,
    known_points,
    nerfies_camera_json,
    nerfies_project,
    project,
    render_rgb,
    ring_camera,
    write_dynerf,
    write_nerfies,
    write_panoptic,
)

PIXEL_TOLERANCE = 0.5


@pytest.fixture(scope="module")
def panoptic(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Truth]:
    folder = tmp_path_factory.mktemp("panoptic")
    return folder, write_panoptic(folder)


@pytest.fixture(scope="module")
def dynerf_folder(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Truth]:
    folder = tmp_path_factory.mktemp("dynerf")
    return folder, write_dynerf(folder)


@pytest.fixture(scope="module")
def nerfies(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Truth]:
    folder = tmp_path_factory.mktemp("nerfies")
    return folder, write_nerfies(folder)


def _check_geometry(split: Split, views: list[tuple[Camera, float]], factor: float = 1.0) -> None:
    """Times match; each camera projects known points where the true one does (scaled
    by `factor` for a downscaled split) within PIXEL_TOLERANCE."""
    assert len(split) == len(views)
    for index, (truth, time) in enumerate(views):
        camera = split.cameras[index]
        assert float(split.times[index]) == pytest.approx(time, abs=1e-6)
        assert (camera.width, camera.height) == (
            round(truth.width * factor),
            round(truth.height * factor),
        )
        points = known_points(time)
        error = np.abs(project(camera, points) - project(truth, points) * factor).max()
        assert error < PIXEL_TOLERANCE, f"view {index}: {error:.3f} px"


def _image_error(split: Split, index: int, camera: Camera, time: float) -> float:
    return float(np.abs(split.images[index].numpy() / 1.0 - render_rgb(camera, time)).mean())


def test_panoptic_parses_to_the_rendered_views(panoptic: tuple[Path, Truth]) -> None:
    folder, truth = panoptic
    scene = parse_panoptic(folder)
    for name in ("train", "test"):
        split = getattr(scene, name)
        _check_geometry(split, truth.views[name])
        for index, (camera, time) in enumerate(truth.views[name]):
            assert _image_error(split, index, camera, time) < 6  # JPEG, quality 98
    assert scene.val is scene.test
    # seg/ (0/1 labels) becomes the masks, scaled to 0/255.
    assert scene.train.masks is not None
    mask = scene.train.masks[0]
    assert tuple(mask.shape) == (24, 32, 1) and set(mask.unique().tolist()) == {0, 255}
    # init_pt_cld.npz: points with their colours, inside the scene box.
    assert scene.point_colors is not None and len(scene.points) == len(scene.point_colors) > 100
    assert 0.0 <= float(scene.point_colors.min()) and float(scene.point_colors.max()) <= 1.0
    lower = torch.tensor(scene.scene_box.lower)
    upper = torch.tensor(scene.scene_box.upper)
    inside = ((scene.points >= lower) & (scene.points <= upper)).all(1).float().mean()
    assert float(inside) > 0.95


def test_panoptic_downscale_and_no_point_cloud(tmp_path: Path) -> None:
    truth = write_panoptic(tmp_path, timesteps=2, seg=False, point_cloud=False)
    scene = parse_panoptic(tmp_path, downscale=2, num_random_points=400, seed=3)
    _check_geometry(scene.train, truth.views["train"], factor=0.5)
    assert tuple(scene.train.images[1].shape) == (12, 16, 3) and scene.train.masks is None
    # Without init_pt_cld.npz: points every train camera sees, colours left to the model.
    assert len(scene.points) == 400 and scene.point_colors is None
    _assert_seen_by_all(scene)


def _assert_seen_by_all(scene: SceneData) -> None:
    points = scene.points.double().numpy()
    for camera in scene.train.cameras:
        uv = project(camera, points)
        w2c = camera.world_to_camera.double().numpy()
        depth = points @ w2c[2, :3] + w2c[2, 3]
        assert (depth > 0).all()
        assert ((uv >= 0) & (uv <= [camera.width, camera.height])).all()


def test_dynerf_parses_llff_poses_and_videos(dynerf_folder: tuple[Path, Truth]) -> None:
    folder, truth = dynerf_folder
    scene = parse_dynerf(folder, num_random_points=300)
    _check_geometry(scene.train, truth.views["train"])
    _check_geometry(scene.test, truth.views["test"])
    assert {float(t) for t in scene.test.times} == {0.0, 0.25, 0.5, 0.75, 1.0}
    # mp4v is lossy: each frame is closest to the render of its own camera and time.
    candidates = truth.views["train"]
    for index in range(len(scene.train)):
        errors = [_image_error(scene.train, index, c, t) for c, t in candidates]
        assert int(np.argmin(errors)) == index and errors[index] < 12
    assert _image_error(scene.test, 3, *truth.views["test"][3]) < 12
    assert len(scene.points) == 300 and scene.point_colors is None
    _assert_seen_by_all(scene)


def test_dynerf_frames_are_decoded_once_into_a_disk_cache(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    folder = tmp_path / "scene"
    write_dynerf(folder, num_cameras=2, frames=3, size=(32, 16))
    decoded: list[str] = []
    original = dynerf._decode

    def counting(video: Path, *args: Any) -> dynerf.FrameCache:
        decoded.append(video.name)
        return original(video, *args)

    monkeypatch.setattr(dynerf, "_decode", counting)
    monkeypatch.delenv("DYNGS_CACHE")
    first = parse_dynerf(folder, downscale=2, num_random_points=50)
    caches = sorted((folder / ".dyngs-cache").glob("*.u8"))
    assert [p.name for p in caches] == ["cam00-x2.u8", "cam01-x2.u8"]
    assert caches[0].stat().st_size == 3 * 8 * 16 * 3  # uint8 frames, already downscaled
    assert sorted(decoded) == ["cam00.mp4", "cam01.mp4"]

    second = parse_dynerf(folder, downscale=2, num_random_points=50)
    assert len(decoded) == 2  # read from the cache
    assert torch.equal(first.train.images[2], second.train.images[2])
    assert tuple(second.train.images[2].shape) == (8, 16, 3)

    stat = (folder / "cam01.mp4").stat()
    os.utime(folder / "cam01.mp4", ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    parse_dynerf(folder, downscale=2, num_random_points=50)
    assert decoded[2:] == ["cam01.mp4"]  # a changed video is decoded again

    monkeypatch.setenv("DYNGS_CACHE", str(tmp_path / "cache"))
    parse_dynerf(folder, downscale=2, num_random_points=50)
    assert len(list((tmp_path / "cache").glob("frames-scene-*/cam0?-x2.u8"))) == 2


def test_nerfies_parses_normalised_cameras(nerfies: tuple[Path, Truth]) -> None:
    folder, truth = nerfies
    scene = parse_nerfies(folder, num_random_points=300)
    for name in ("train", "test"):
        split = getattr(scene, name)
        _check_geometry(split, truth.views[name])
        for index, (camera, time) in enumerate(truth.views[name]):
            assert _image_error(split, index, camera, time) == 0  # PNG, no distortion
    assert scene.val is scene.test
    # The same points, given in the file's world, project as Nerfies' own model says.
    world = NerfiesWorld()
    for index, (camera, time) in enumerate(truth.views["train"]):
        points = known_points(time)
        expected = nerfies_project(nerfies_camera_json(camera, world, 1.1), world.to_world(points))
        error = np.abs(project(scene.train.cameras[index], points) - expected).max()
        assert error < PIXEL_TOLERANCE
    _assert_seen_by_all(scene)


def test_nerfies_reads_the_matching_rgb_folder(nerfies: tuple[Path, Truth]) -> None:
    folder, truth = nerfies
    half = parse_nerfies(folder, downscale=2, num_random_points=10)
    assert half.train.paths is not None and half.train.paths[0].parent.name == "2x"
    _check_geometry(half.train, truth.views["train"], factor=0.5)
    quarter = parse_nerfies(folder, downscale=4, num_random_points=10)  # 2x, shrunk again
    assert quarter.train.paths is not None and quarter.train.paths[0].parent.name == "2x"
    _check_geometry(quarter.train, truth.views["train"], factor=0.25)
    assert tuple(quarter.train.images[0].shape) == (6, 8, 3)
    third = parse_nerfies(folder, downscale=3, num_random_points=10)  # 1x, shrunk by 3
    assert third.train.paths is not None and third.train.paths[0].parent.name == "1x"
    assert (
        tuple(third.train.images[0].shape)
        == (8, 11, 3)
        == (
            third.train.cameras[0].height,
            third.train.cameras[0].width,
            3,
        )
    )


def test_nerfies_points_and_times(tmp_path: Path) -> None:
    world = NerfiesWorld(center=(5.0, 0.0, -3.0), scale=2.0)
    truth = write_nerfies(tmp_path, frames=6, world=world, val_every=3, scales=(1,), points=True)
    metadata = json.loads((tmp_path / "metadata.json").read_text())
    for entry in metadata.values():  # time_id wins over warp_id; its range maps to [0, 1]
        entry["time_id"] = 10 + 2 * entry["warp_id"]
        entry["warp_id"] = 0
    (tmp_path / "metadata.json").write_text(json.dumps(metadata))
    scene = parse_nerfies(tmp_path)
    _check_geometry(scene.train, truth.views["train"])
    assert scene.train.times.tolist() == pytest.approx([0.0, 0.2, 0.6, 0.8])
    # points.npy is in world units: it comes back in the normalised (procedural) space.
    assert float(scene.points.abs().max()) < 1.5 and scene.point_colors is None


def _blob_image(
    lens: dict, centres: np.ndarray, size: tuple[int, int], sigma: float = 1.2
) -> np.ndarray:
    """Gaussian dots (peak 255) centred on `centres` (pixels, centres at +0.5)."""
    width, height = size
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    image = np.zeros((height, width))
    for cu, cv in centres:
        image += np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * sigma**2))
    gray = np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)
    return np.repeat(gray[:, :, None], 3, axis=2)


def test_nerfies_images_are_undistorted_on_load(tmp_path: Path) -> None:
    """Dots drawn where Nerfies' distorted model puts known points end up, after loading,
    where the parsed pinhole camera projects them."""
    size = (96, 72)
    camera = ring_camera(0.4, math.radians(30), size, focal=(45.0, 45.0), principal=(49.0, 35.0))
    world = NerfiesWorld(center=(0.0, 0.0, 0.0), scale=1.0)
    lens = {"radial_distortion": [-0.35, 0.1, -0.02], "tangential_distortion": [0.01, -0.008]}
    json_camera = nerfies_camera_json(camera, world, 1.0, lens)
    # A grid of points on the plane through the origin facing the camera.
    w2c = camera.world_to_camera.double().numpy()
    right, down = w2c[0, :3], w2c[1, :3]
    grid = [a * right + b * down for a in (-1.5, -0.5, 0.5, 1.5) for b in (-1.0, 0.0, 1.0)]
    points = np.array(grid)
    distorted = nerfies_project(json_camera, points)
    assert np.abs(distorted - project(camera, points)).max() > 2  # the lens matters
    write_nerfies(tmp_path, frames=2, size=size, world=world, val_every=2, scales=(1,))
    cv2.imwrite(
        str(tmp_path / "rgb" / "1x" / "000000.png"), _blob_image(json_camera, distorted, size)
    )
    del json_camera["tangential_distortion"]  # Nerfies' own files name it `tangential`
    json_camera["tangential"] = lens["tangential_distortion"]
    (tmp_path / "camera" / "000000.json").write_text(json.dumps(json_camera))

    scene = parse_nerfies(tmp_path, num_random_points=10)
    parsed = scene.train.cameras[0]
    image = scene.train.images[0].numpy()[:, :, 0].astype(np.float64)
    for expected in project(parsed, points):
        u0, v0 = (int(c) for c in expected)
        window = image[v0 - 4 : v0 + 5, u0 - 4 : u0 + 5]
        vs, us = np.mgrid[v0 - 4 : v0 + 5, u0 - 4 : u0 + 5] + 0.5
        centroid = np.array([(window * us).sum(), (window * vs).sum()]) / window.sum()
        assert np.abs(centroid - expected).max() < PIXEL_TOLERANCE, (centroid, expected)


@pytest.mark.parametrize(
    ("name", "writer", "marker"),
    [
        ("panoptic", write_panoptic, "train_meta.json"),
        ("dynerf", write_dynerf, "poses_bounds.npy"),
        ("nerfies", write_nerfies, "dataset.json"),
    ],
)
def test_format_is_found_automatically_or_by_name(
    name: str, writer: object, marker: str, tmp_path: Path
) -> None:
    folder = tmp_path / "capture"
    folder.mkdir()
    assert callable(writer)
    writer(folder)
    auto = load_scene(folder, DataConfig(num_random_points=20))
    named = load_scene(folder, DataConfig(num_random_points=20, format=name))
    assert len(auto.train) == len(named.train) > 0
    with pytest.raises(DatasetError, match=r"transforms_train\.json: missing"):
        load_scene(folder, DataConfig(format="dnerf"))
    shutil.move(folder / marker, tmp_path / marker)
    with pytest.raises(DatasetError, match="not a dataset folder"):
        load_scene(folder, DataConfig())


def test_format_flag_rejects_unknown_names() -> None:
    with pytest.raises(ConfigError, match=r"--format must be one of auto, dnerf, panoptic"):
        DataConfig(format="llff")


def test_loading_reports_what_it_found(
    panoptic: tuple[Path, Truth], capsys: pytest.CaptureFixture[str]
) -> None:
    load_scene(panoptic[0], DataConfig())
    found, points = capsys.readouterr().err.strip().splitlines()
    assert found.startswith("panoptic ")
    for part in ("5 cameras", "3 timestamps", "12 train / 3 val / 3 test", "32×24", "t ∈ [0, 1]"):
        assert part in found
    # The second line says where the Gaussians start: here, the capture's own cloud.
    assert points.startswith("[points]") and "from init_pt_cld.npz" in points

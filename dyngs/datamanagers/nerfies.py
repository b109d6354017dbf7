"""The Nerfies / HyperNeRF capture layout (Park et al. 2021), as `nerfies/camera.py` and
`nerfies/datasets/nerfies.py` of google/nerfies read it.

Files:

- `dataset.json`: `train_ids` and `val_ids` (frame ids; `ids` lists them all).
- `metadata.json`: per id a `time_id` or `warp_id` (the frame's time index) and a
  `camera_id`.
- `camera/<id>.json`: `orientation` (3×3 world-to-camera rotation: its rows are the
  camera's x right, y down, z forward axes in world space, OpenCV axes), `position`
  (the camera centre in world space), `focal_length` (pixels, at 1x),
  `pixel_aspect_ratio` (fy = focal_length · ratio), `principal_point` (cx, cy),
  `skew`, `radial_distortion` (k1, k2, k3), `tangential_distortion` (p1, p2; Nerfies'
  own files name it `tangential`) and `image_size` (width, height at 1x).
- `rgb/<k>x/<id>.png`: the frames at 1/k size (1x, 2x, 4x, …).
- `scene.json`: `center`, `scale`, `near`, `far`. Nerfies trains in the normalised space
  x' = (x − center) · scale, where `near` and `far` are given.
- `points.npy` (optional): [P, 3] points in world space.

Conventions:

- Projection (Nerfies' `Camera.project`): for a point with camera coordinates
  (x, y, z), normalised (x/z, y/z) is distorted by the radial-tangential model of OpenCV
  (`dyngs.datamanagers.images.Lens`) to (x', y'), then pixel = (f x' + skew y' + cx,
  f·ratio·y' + cy), pixel centres at +0.5 (Nerfies' `get_pixel_centers`).
- Resolution: `--downscale d` reads `rgb/<d>x` when it exists, else the largest `rgb/<k>x`
  with k dividing d, shrunk by d / k. Intrinsics are scaled by the ratio of the image's
  actual size to `image_size`, per axis (Nerfies scales them by 1/k; skew, which Nerfies
  leaves unscaled and the released captures set to 0, is scaled with x).
- Distortion: every image is undistorted when it is read, by resampling it into the
  pinhole camera with the same focal lengths and principal point and no skew; that
  pinhole camera is the one the split holds.
- Space: cameras and points are mapped into Nerfies' normalised space, so the scene box
  and the learning rates see the scale Nerfies trains at: the centre moves to
  (position − center) · scale, the rotation is unchanged.
- Times: the time indices (`time_id`, else `warp_id`) of all ids, mapped linearly from
  their min..max onto [0, 1].
- Splits: `val_ids` are the test views (validation uses them too). When `val_ids` is
  empty (HyperNeRF's single-camera captures), every eighth train id, starting at the
  fifth, is held out instead.
- Initial points: `points.npy` when present, else uniform in the volume every train
  camera sees between `near` and `far`.

Images are read lazily (decode, undistort, downscale on first use; the uint8 frames kept
in memory total at most `cache_bytes`). Every problem with the input raises a one-line
DatasetError naming the file.

Letters: F frames, H×W image, P points.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from jaxtyping import UInt8

from dyngs.datamanagers.base import (
    HOST_CACHE_BYTES,
    LazyImages,
    SceneData,
    Split,
    capture_folder,
)
from dyngs.datamanagers.cameras import (
    check_rigid,
    points_in_common_view,
    rotation_center_to_world_to_camera,
    scene_box_from_cameras,
)
from dyngs.datamanagers.files import array, load_json, load_npy, number, require, whole
from dyngs.datamanagers.images import (
    Lens,
    composite,
    downscale,
    png_size,
    read_image,
    undistort,
)
from dyngs.datamanagers.progress import progress_bar
from dyngs.errors import DatasetError
from dyngs.types import Camera

HOLDOUT_EVERY = 8
"""With no val_ids, every this-many-th train id is held out for testing."""


@dataclass(frozen=True)
class _Scene:
    center: np.ndarray
    scale: float
    near: float
    far: float


@dataclass(frozen=True)
class _View:
    """One frame: its pinhole camera (after undistortion, before the residual
    downscale), the lens it was taken through, and where its image is."""

    id: str
    camera: Camera
    lens: Lens
    image: Path


def _read_scene(path: Path) -> _Scene:
    data = load_json(path)
    where = str(path)
    center = array(require(data, "center", where), "center", where, (3,))
    scale = number(require(data, "scale", where), "scale", where, positive=True)
    near = number(require(data, "near", where), "near", where)
    far = number(require(data, "far", where), "far", where)
    if not 0 <= near < far:
        raise DatasetError(f"{where}: need 0 ≤ near < far, got near={near}, far={far}")
    return _Scene(center, scale, near, far)


def _ids(data: dict[str, Any], key: str, where: str) -> list[str]:
    value = require(data, key, where)
    if not isinstance(value, list) or not all(isinstance(v, str | int) for v in value):
        raise DatasetError(f"{where}: '{key}' must be a list of ids")
    ids = [str(v) for v in value]
    if len(set(ids)) != len(ids):
        raise DatasetError(f"{where}: '{key}' lists an id twice")
    return ids


def _time_indices(path: Path, ids: list[str]) -> dict[str, float]:
    """Each id's time index: `time_id` when every entry has one, else `warp_id`."""
    metadata = load_json(path)
    entries: dict[str, dict[str, Any]] = {}
    for frame_id in ids:
        entry = metadata.get(frame_id)
        if not isinstance(entry, dict):
            raise DatasetError(f"{path}: no entry (object) for id {frame_id!r}")
        entries[frame_id] = entry
    key = "time_id" if all("time_id" in e for e in entries.values()) else "warp_id"
    indices: dict[str, float] = {}
    for frame_id, entry in entries.items():
        where = f"{path}: id {frame_id!r}"
        indices[frame_id] = number(require(entry, key, where), key, where)
    return indices


def _rgb_folder(folder: Path, factor: int) -> tuple[Path, int, int]:
    """(folder, k, residual): the `rgb/<k>x` to read and the factor still to apply."""
    rgb = folder / "rgb"
    available = sorted(
        int(p.name[:-1])
        for p in (rgb.iterdir() if rgb.is_dir() else [])
        if p.is_dir() and p.name.endswith("x") and p.name[:-1].isdigit() and int(p.name[:-1]) > 0
    )
    usable = [k for k in available if factor % k == 0]
    if not usable:
        found = ", ".join(f"{k}x" for k in available) or "none"
        raise DatasetError(
            f"{rgb}: no {factor}x folder, nor one whose factor divides {factor} (found {found})"
        )
    k = usable[-1]
    return rgb / f"{k}x", k, factor // k


def _read_camera(path: Path, scene: _Scene, image: Path, k: int) -> tuple[Camera, Lens]:
    """The undistorted pinhole camera (normalised space) at the size of `image`, which
    should be the 1x image_size divided by k."""
    data = load_json(path)
    where = str(path)
    rotation = array(require(data, "orientation", where), "orientation", where, (3, 3))
    position = array(require(data, "position", where), "position", where, (3,))
    focal = number(require(data, "focal_length", where), "focal_length", where, positive=True)
    principal = array(require(data, "principal_point", where), "principal_point", where, (2,))
    full_width, full_height = (
        whole(v, "image_size", where)
        for v in array(require(data, "image_size", where), "image_size", where, (2,))
    )
    skew = number(data.get("skew", 0.0), "skew", where)
    ratio = number(data.get("pixel_aspect_ratio", 1.0), "pixel_aspect_ratio", where, positive=True)
    radial = data.get("radial_distortion", [0.0, 0.0, 0.0])
    if not isinstance(radial, list) or not 1 <= len(radial) <= 3:
        raise DatasetError(f"{where}: radial_distortion must be 1 to 3 numbers (k1, k2, k3)")
    ks = [number(v, "radial_distortion", where) for v in radial] + [0.0] * (3 - len(radial))
    tangential_key = "tangential_distortion" if "tangential_distortion" in data else "tangential"
    tangential = data.get(tangential_key, [0.0, 0.0])
    ps = array(tangential, tangential_key, where, (2,))
    pose = np.eye(4)
    pose[:3, :3] = rotation
    checked = check_rigid(pose, "orientation")
    if isinstance(checked, str):
        raise DatasetError(f"{where}: {checked}")

    size = png_size(image)
    if size is None:  # not a PNG after all: decode it to learn its size
        decoded = read_image(image)
        size = (decoded.shape[1], decoded.shape[0])
    width, height = size
    if abs(width - full_width / k) > 1 or abs(height - full_height / k) > 1:
        raise DatasetError(
            f"{image}: image is {width}×{height} but {path} gives image_size "
            f"{full_width}×{full_height}, i.e. {full_width / k:g}×{full_height / k:g} at {k}x"
        )
    sx, sy = width / full_width, height / full_height
    lens = Lens(
        fx=focal * sx,
        fy=focal * ratio * sy,
        cx=float(principal[0]) * sx,
        cy=float(principal[1]) * sy,
        skew=skew * sx,
        k1=ks[0],
        k2=ks[1],
        k3=ks[2],
        p1=float(ps[0]),
        p2=float(ps[1]),
    )
    center = (position - scene.center) * scene.scale
    w2c = rotation_center_to_world_to_camera(rotation, center)
    try:
        camera = Camera(
            lens.fx, lens.fy, lens.cx, lens.cy, torch.from_numpy(w2c).float(), width, height
        )
    except ValueError as error:
        raise DatasetError(f"{where}: {error}") from None
    return camera, lens


def _load(
    view: _View, residual: int, background: tuple[float, float, float]
) -> UInt8[np.ndarray, "H W 3"]:
    image = read_image(view.image)
    camera = view.camera
    if image.shape[:2] != (camera.height, camera.width):
        raise DatasetError(
            f"{view.image}: image is {image.shape[1]}×{image.shape[0]}, "
            f"expected {camera.width}×{camera.height}"
        )
    if image.shape[2] == 4:
        image = composite(image, background)
    if not view.lens.is_pinhole:
        pinhole = (camera.fx, camera.fy, camera.cx, camera.cy)
        image = undistort(image, view.lens, pinhole, (camera.width, camera.height))
    return downscale(image, residual)


def _split(
    views: list[_View],
    times: dict[str, float],
    residual: int,
    background: tuple[float, float, float],
    cache_bytes: int,
) -> Split:
    cameras = [v.camera.scaled(1.0 / residual) if residual > 1 else v.camera for v in views]
    # downscale() and Camera.scaled round sizes alike, so these are the loaded sizes.
    sizes = [(c.height, c.width) for c in cameras]
    return Split(
        cameras=cameras,
        times=torch.tensor([times[v.id] for v in views], dtype=torch.float32),
        images=LazyImages(lambda i: _load(views[i], residual, background), sizes, 3, cache_bytes),
        paths=[v.image for v in views],
    )


def _read_points(path: Path, scene: _Scene) -> torch.Tensor:
    data = load_npy(path)
    if data.ndim != 2 or data.shape[1] != 3 or data.dtype.kind not in "fiu":
        raise DatasetError(
            f"{path}: need a float array [points, 3], got {data.dtype} {list(data.shape)}"
        )
    points = data.astype(np.float64)
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) == 0:
        raise DatasetError(f"{path}: no point with finite coordinates")
    return torch.from_numpy((points - scene.center) * scene.scale).float()


def _split_ids(dataset_path: Path) -> tuple[list[str], list[str]]:
    """dataset.json's train and val ids; without val ids, every HOLDOUT_EVERY-th train id
    is held out."""
    dataset = load_json(dataset_path)
    train_ids = _ids(dataset, "train_ids", str(dataset_path))
    val_ids = _ids(dataset, "val_ids", str(dataset_path))
    if not train_ids:
        raise DatasetError(f"{dataset_path}: 'train_ids' is empty")
    if not val_ids:
        val_ids = train_ids[HOLDOUT_EVERY // 2 :: HOLDOUT_EVERY]
        train_ids = [i for i in train_ids if i not in set(val_ids)]
        if not train_ids or not val_ids:
            raise DatasetError(
                f"{dataset_path}: too few train_ids to hold some out (val_ids is empty)"
            )
    return train_ids, val_ids


def parse_nerfies(
    path: Path,
    downscale: int = 1,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    num_random_points: int = 20_000,
    seed: int = 0,
    cache_bytes: int = HOST_CACHE_BYTES,
) -> SceneData:
    """Read a Nerfies / HyperNeRF capture folder; see the module docstring."""
    path = capture_folder(path, downscale)
    dataset_path = path / "dataset.json"
    train_ids, val_ids = _split_ids(dataset_path)
    scene = _read_scene(path / "scene.json")
    indices = _time_indices(path / "metadata.json", train_ids + val_ids)
    low, high = min(indices.values()), max(indices.values())
    times = {i: (v - low) / (high - low) if high > low else 0.0 for i, v in indices.items()}
    folder, k, residual = _rgb_folder(path, downscale)

    views: dict[str, _View] = {}
    with progress_bar() as progress:
        task = progress.add_task(f"reading {path.name} cameras", total=len(times))
        for frame_id in train_ids + val_ids:
            image = folder / f"{frame_id}.png"
            if not image.is_file():
                raise DatasetError(
                    f"{image}: missing image (id {frame_id!r} of {dataset_path.name})"
                )
            camera, lens = _read_camera(path / "camera" / f"{frame_id}.json", scene, image, k)
            views[frame_id] = _View(frame_id, camera, lens, image)
            progress.advance(task)
    # Three quarters of the host cache for the train split, a quarter for the test split.
    train_bytes = cache_bytes - cache_bytes // 4
    train = _split([views[i] for i in train_ids], times, residual, background, train_bytes)
    test = _split([views[i] for i in val_ids], times, residual, background, cache_bytes // 4)

    source = "random in the cameras' common view"
    if (path / "points.npy").is_file():
        points = _read_points(path / "points.npy", scene)
        source = "points.npy"
    else:
        depths = [(scene.near, scene.far)] * len(train)
        points = points_in_common_view(train.cameras, depths, num_random_points, seed)
    return SceneData(
        name=path.resolve().name,
        train=train,
        val=test,
        test=test,
        scene_box=scene_box_from_cameras(train.cameras, points),
        points=points,
        point_colors=None,
        background=torch.tensor(background, dtype=torch.float32),
        points_source=source,
    )

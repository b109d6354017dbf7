"""The D-NeRF / Blender format: transforms_{train,val,test}.json plus images.

Each JSON holds `camera_angle_x` and/or pinhole intrinsics `fl_x, fl_y, cx, cy, w, h`
(top level or per frame; per frame wins) and a list of `frames`, each with a
`file_path` (relative to the folder, usually without extension), a `time` in [0, 1]
and a camera-to-world `transform_matrix` in the Blender/OpenGL convention (x right,
y up, looking down −z). A missing val split falls back to the test split. Other keys
(`rotation`) and folders (the MuJoCo scenes' per-class `masks/`) are ignored.

Every problem with the input raises a one-line DatasetError naming the file.

Letters: F frames, H×W image, P points.
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from jaxtyping import Float, UInt8

from dyngs.datamanagers.base import SceneData, Split, capture_folder
from dyngs.datamanagers.cameras import (
    blender_to_world_to_camera,
    check_rigid,
    random_points_in_box,
    scene_box_from_cameras,
)
from dyngs.datamanagers.files import load_json
from dyngs.datamanagers.images import composite, downscale, read_image
from dyngs.datamanagers.progress import progress_bar
from dyngs.errors import DatasetError
from dyngs.ply import read_ply
from dyngs.types import Camera

SPLITS = ("train", "val", "test")
POINT_CLOUD_NAMES = ("fused.ply", "points3d.ply")
"""Initial point clouds looked for at the top of the folder, in this order."""


@dataclass
class _Frame:
    """One frame's metadata, checked before any image is read."""

    json_path: Path
    index: int
    file_path: str
    image_path: Path
    time: float
    world_to_camera: Float[np.ndarray, "4 4"]
    intrinsics: dict[str, float]
    """Any of fl_x, fl_y, cx, cy, w, h, camera_angle_x given for this frame."""

    def error(self, problem: str) -> DatasetError:
        return DatasetError(f"{self.json_path}: frame {self.index} ({self.file_path}): {problem}")


_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x")
_POSITIVE_KEYS = ("fl_x", "fl_y", "w", "h", "camera_angle_x")


def _intrinsics(source: dict[str, Any], where: str) -> dict[str, float]:
    """The intrinsic keys present in `source`, checked to be finite numbers."""
    found: dict[str, float] = {}
    for key in _INTRINSIC_KEYS:
        if key not in source:
            continue
        value = source[key]
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise DatasetError(f"{where}: {key} must be a number, got {value!r}")
        if not math.isfinite(value):
            raise DatasetError(f"{where}: {key} is not finite ({value})")
        if key in _POSITIVE_KEYS and value <= 0:
            raise DatasetError(f"{where}: {key} must be positive, got {value}")
        if key in ("w", "h") and value != int(value):
            raise DatasetError(f"{where}: {key} must be a whole number of pixels, got {value}")
        if key == "camera_angle_x" and value >= math.pi:
            raise DatasetError(f"{where}: camera_angle_x must be below π radians, got {value}")
        found[key] = float(value)
    return found


def _image_file(folder: Path, file_path: str) -> Path | None:
    """The image a frame's file_path names: as given, else with .png appended."""
    base = folder / file_path
    for candidate in (base, base.with_name(base.name + ".png")):
        if candidate.is_file():
            return candidate
    return None


def _read_frames(folder: Path, json_path: Path) -> list[_Frame]:
    data = load_json(json_path)
    if "frames" not in data:
        raise DatasetError(f"{json_path}: no 'frames' list")
    frames = data["frames"]
    if not isinstance(frames, list):
        raise DatasetError(f"{json_path}: 'frames' must be a list, got {type(frames).__name__}")
    if not frames:
        raise DatasetError(f"{json_path}: 'frames' is empty")
    shared = _intrinsics(data, str(json_path))
    result: list[_Frame] = []
    seen: dict[Path, int] = {}
    for index, frame in enumerate(frames):
        where = f"{json_path}: frame {index}"
        if not isinstance(frame, dict):
            raise DatasetError(f"{where}: must be a JSON object, got {type(frame).__name__}")
        for key in ("file_path", "time", "transform_matrix"):
            if key not in frame:
                raise DatasetError(f"{where}: missing '{key}'")
        file_path = frame["file_path"]
        if not isinstance(file_path, str) or not file_path:
            raise DatasetError(f"{where}: file_path must be a non-empty string, got {file_path!r}")
        where = f"{json_path}: frame {index} ({file_path})"
        time = frame["time"]
        if isinstance(time, bool) or not isinstance(time, int | float):
            raise DatasetError(f"{where}: time must be a number, got {time!r}")
        if not math.isfinite(time) or not 0.0 <= time <= 1.0:
            raise DatasetError(f"{where}: time must be finite and in [0, 1], got {time}")
        c2w = check_rigid(frame["transform_matrix"])
        if isinstance(c2w, str):
            raise DatasetError(f"{where}: {c2w}")
        image_path = _image_file(folder, file_path)
        if image_path is None:
            raise DatasetError(
                f"{where}: missing image {folder / file_path} (also tried with .png appended)"
            )
        resolved = image_path.resolve()
        if resolved in seen:
            raise DatasetError(
                f"{where}: duplicate image {image_path.name}, also used by frame {seen[resolved]}"
            )
        seen[resolved] = index
        intrinsics = {**shared, **_intrinsics(frame, where)}
        if not {"fl_x", "camera_angle_x"} & intrinsics.keys():
            raise DatasetError(f"{where}: no focal length (need fl_x or camera_angle_x)")
        result.append(
            _Frame(
                json_path,
                index,
                file_path,
                image_path,
                float(time),
                blender_to_world_to_camera(c2w),
                intrinsics,
            )
        )
    return result


def _camera(frame: _Frame, width: int, height: int) -> Camera:
    """The frame's camera for its full-size image (width × height as read from disk)."""
    k = frame.intrinsics
    for key, actual in (("w", width), ("h", height)):
        if key in k and int(k[key]) != actual:
            raise frame.error(
                f"image {frame.image_path.name} is {width}×{height} but the JSON gives "
                f"{key}={int(k[key])}"
            )
    if "fl_x" in k:
        fx = k["fl_x"]
        fy = k.get("fl_y", fx)
    else:
        fx = fy = 0.5 * width / math.tan(0.5 * k["camera_angle_x"])
    cx = k.get("cx", width / 2)
    cy = k.get("cy", height / 2)
    w2c = torch.from_numpy(frame.world_to_camera).float()
    try:
        return Camera(fx, fy, cx, cy, w2c, width, height)
    except ValueError as error:
        raise frame.error(str(error)) from None


def _load_image(
    frame: _Frame, background: tuple[float, float, float], factor: int
) -> tuple[UInt8[np.ndarray, "H W 3"], UInt8[np.ndarray, "H W 1"] | None, tuple[int, int]]:
    """Composited, downscaled RGB, the downscaled alpha (if any) and the full size (w, h)."""
    image = read_image(frame.image_path)
    height, width = image.shape[:2]
    alpha: np.ndarray | None = None
    if image.shape[2] == 4:
        alpha = downscale(image[:, :, 3:], factor)
        image = composite(image, background)
    return downscale(image, factor), alpha, (width, height)


def find_point_cloud(folder: Path) -> Path | None:
    """fused.ply, points3d.ply or the only *.ply at the top of `folder`, if any."""
    for name in POINT_CLOUD_NAMES:
        if (folder / name).is_file():
            return folder / name
    candidates = sorted(p for p in folder.glob("*.ply") if p.is_file())
    return candidates[0] if len(candidates) == 1 else None


def read_point_cloud(
    path: Path,
) -> tuple[Float[torch.Tensor, "P 3"], Float[torch.Tensor, "P 3"] | None]:
    """Positions and (when the PLY has red/green/blue) colours in [0, 1] of a point cloud.

    Points with a non-finite coordinate are dropped.
    """
    vertex = read_ply(path)
    missing = [axis for axis in "xyz" if axis not in vertex]
    if missing:
        raise DatasetError(f"{path}: PLY vertices have no {'/'.join(missing)} coordinate")
    xyz = np.stack([vertex[axis] for axis in "xyz"], axis=1).astype(np.float64)
    keep = np.isfinite(xyz).all(axis=1)
    if not keep.any():
        raise DatasetError(f"{path}: PLY has no vertex with finite coordinates")
    points = torch.from_numpy(xyz[keep]).float()
    if not all(channel in vertex for channel in ("red", "green", "blue")):
        return points, None
    rgb = np.stack([vertex[c] for c in ("red", "green", "blue")], axis=1)
    if rgb.dtype.kind in "ui":
        rgb = rgb.astype(np.float64) / float(np.iinfo(rgb.dtype).max)
    colors = np.clip(np.nan_to_num(rgb.astype(np.float64)), 0.0, 1.0)
    return points, torch.from_numpy(colors[keep]).float()


def parse_dnerf(
    path: Path,
    downscale: int = 1,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    num_random_points: int = 20_000,
    seed: int = 0,
) -> SceneData:
    """Read a D-NeRF / Blender dataset folder.

    RGBA images are composited over `background` (their alpha becomes the split's mask);
    RGB images are used as they are. All images must share one size. Initial points come
    from `fused.ply`, `points3d.ply` or the single *.ply at the top of the folder, else
    `num_random_points` uniform random points in the scene box (seeded by `seed`).
    """
    path = capture_folder(path, downscale)
    json_paths = {split: path / f"transforms_{split}.json" for split in SPLITS}
    for split in ("train", "test"):
        if not json_paths[split].is_file():
            raise DatasetError(f"{json_paths[split]}: missing (a D-NeRF folder needs it)")
    # Read and check all metadata before any image, so bad input fails fast.
    frames = {
        split: _read_frames(path, json_paths[split])
        for split in SPLITS
        if json_paths[split].is_file()
    }
    splits = _load_splits(path, frames, background, downscale)
    if "val" not in splits:
        splits["val"] = splits["test"]

    points: torch.Tensor | None = None
    colors: torch.Tensor | None = None
    cloud = find_point_cloud(path)
    source = "random in the box"
    if cloud is not None:
        points, colors = read_point_cloud(cloud)
        source = cloud.name
    box = scene_box_from_cameras(splits["train"].cameras, points)
    if points is None:
        points = random_points_in_box(box, num_random_points, seed)
    return SceneData(
        name=path.resolve().name,
        train=splits["train"],
        val=splits["val"],
        test=splits["test"],
        scene_box=box,
        points=points,
        point_colors=colors,
        background=torch.tensor(background, dtype=torch.float32),
        points_source=source,
    )


def _load_splits(
    folder: Path,
    frames: dict[str, list[_Frame]],
    background: tuple[float, float, float],
    factor: int,
) -> dict[str, Split]:
    """Read every split's images (decoded in threads: OpenCV releases the GIL)."""
    pool = ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1))
    try:
        with progress_bar() as progress:
            total = sum(len(f) for f in frames.values())
            task = progress.add_task(f"loading {folder.name}", total=total)
            reference: tuple[int, int, Path] | None = None  # the first image's w, h, path
            splits: dict[str, Split] = {}
            for split, split_frames in frames.items():
                loaded = pool.map(lambda f: _load_image(f, background, factor), split_frames)
                cameras: list[Camera] = []
                images: list[torch.Tensor] = []
                alphas: list[np.ndarray | None] = []
                for frame, (rgb, alpha, size) in zip(split_frames, loaded, strict=True):
                    if reference is None:
                        reference = (*size, frame.image_path)
                    elif size != reference[:2]:
                        raise frame.error(
                            f"image {frame.image_path.name} is {size[0]}×{size[1]} but the "
                            f"first image ({reference[2]}) is {reference[0]}×{reference[1]}"
                        )
                    camera = _camera(frame, *size)
                    cameras.append(camera.scaled(1.0 / factor) if factor > 1 else camera)
                    images.append(torch.from_numpy(np.ascontiguousarray(rgb)))
                    alphas.append(alpha)
                    progress.advance(task)
                splits[split] = Split(
                    cameras=cameras,
                    times=torch.tensor([f.time for f in split_frames], dtype=torch.float32),
                    images=images,
                    masks=_masks(alphas, images),
                    paths=[f.image_path for f in split_frames],
                )
            return splits
    finally:
        # After an error (or Ctrl-C) drop the decodes still queued rather than wait for them.
        pool.shutdown(wait=True, cancel_futures=True)


def _masks(
    alphas: list[UInt8[np.ndarray, "H W 1"] | None], images: list[UInt8[torch.Tensor, "H W 3"]]
) -> list[UInt8[torch.Tensor, "H W 1"]] | None:
    """The split's alpha masks: None when no image had alpha, opaque for those without."""
    if all(alpha is None for alpha in alphas):
        return None
    return [
        torch.from_numpy(np.ascontiguousarray(alpha))
        if alpha is not None
        else torch.full((*image.shape[:2], 1), 255, dtype=torch.uint8)
        for alpha, image in zip(alphas, images, strict=True)
    ]

"""The Panoptic-sports layout of Dynamic 3D Gaussians (Luiten et al. 2024).

Files, as that project's `train.py` reads them:

- `train_meta.json`, `test_meta.json`: `w`, `h` (image size in pixels) and four nested
  lists indexed [timestep t][view i]: `k` (3×3 pinhole intrinsics, pixel centres at
  +0.5 as in every 3DGS rasterizer), `w2c` (4×4 world-to-camera, OpenCV axes),
  `fn` (image path relative to `ims/`, e.g. "0/000000.jpg") and `cam_id` (which fixed
  camera took it).
- `ims/<fn>`: the RGB frames.
- `seg/<fn with .png>` (optional): foreground segmentation, 0/1 or 0/255. It becomes the
  split's masks, i.e. the weights of the photometric loss.
- `init_pt_cld.npz` (optional): array `data`, one row per point: x, y, z, r, g, b
  (colours in [0, 1]; 0–255 is recognised and rescaled), segmentation.

Times: timestep t of T becomes t / (T − 1); train and test share the denominator (the
larger T of the two files), so equal timesteps get equal times. The test split is
`test_meta.json`, and validation uses it too. Without a point cloud the initial points
are uniform in the volume every train camera sees, between depths bounding the scene
box the cameras imply (`points_in_common_view`).

Images are read lazily (JPEG decode and downscale on first use; the uint8 frames kept
in memory total at most `cache_bytes`, three quarters of it for the train split). Every
problem with the input raises a one-line DatasetError naming the file.

Letters: T timesteps, C views per timestep, H×W image, P points.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from jaxtyping import Float, UInt8

from dyngs.datamanagers.base import (
    HOST_CACHE_BYTES,
    LazyImages,
    SceneData,
    Split,
    capture_folder,
)
from dyngs.datamanagers.cameras import (
    check_rigid,
    depth_ranges_around_box,
    points_in_common_view,
    scene_box_from_cameras,
)
from dyngs.datamanagers.files import array, load_json, require, whole
from dyngs.datamanagers.images import composite, downscale, downscaled_size, read_image
from dyngs.datamanagers.progress import progress_bar
from dyngs.errors import DatasetError
from dyngs.types import Camera

META_FILES = {"train": "train_meta.json", "test": "test_meta.json"}
POINT_CLOUD = "init_pt_cld.npz"
_KEYS = ("k", "w2c", "fn", "cam_id")


@dataclass(frozen=True)
class _View:
    """One image's metadata, checked before any pixel is read."""

    timestep: int
    camera_id: int
    camera: Camera
    """At full resolution."""
    image: Path
    mask: Path | None


@dataclass(frozen=True)
class _Meta:
    path: Path
    width: int
    height: int
    views: list[_View]
    num_timesteps: int


def _nested(meta: dict[str, Any], key: str, where: str) -> list[list[Any]]:
    value = require(meta, key, where)
    if not isinstance(value, list) or not value:
        raise DatasetError(f"{where}: '{key}' must be a non-empty list (one entry per timestep)")
    for t, row in enumerate(value):
        if not isinstance(row, list) or not row:
            raise DatasetError(f"{where}: {key}[{t}] must be a non-empty list (one per view)")
    return value


def _intrinsics(value: object, where: str) -> tuple[float, float, float, float]:
    k = array(value, "k", where, (3, 3))
    skewed = abs(k[0, 1]) > 1e-6 * abs(k[0, 0]) or abs(k[1, 0]) > 1e-6 * abs(k[1, 1])
    if skewed or np.abs(k[2] - (0.0, 0.0, 1.0)).max() > 1e-6:
        raise DatasetError(
            f"{where}: k must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {k.tolist()}"
        )
    return float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])


def _read_meta(folder: Path, path: Path, masks: bool) -> _Meta:
    meta = load_json(path)
    where = str(path)
    width = whole(require(meta, "w", where), "w", where)
    height = whole(require(meta, "h", where), "h", where)
    lists = {key: _nested(meta, key, where) for key in _KEYS}
    num_timesteps = len(lists["fn"])
    for key in _KEYS:
        if len(lists[key]) != num_timesteps:
            raise DatasetError(
                f"{where}: '{key}' has {len(lists[key])} timesteps but 'fn' has {num_timesteps}"
            )
    views: list[_View] = []
    for t in range(num_timesteps):
        count = len(lists["fn"][t])
        for key in _KEYS:
            if len(lists[key][t]) != count:
                raise DatasetError(
                    f"{where}: {key}[{t}] has {len(lists[key][t])} views but fn[{t}] has {count}"
                )
        for i in range(count):
            at = f"{where}: [{t}][{i}]"
            fn = lists["fn"][t][i]
            if not isinstance(fn, str) or not fn:
                raise DatasetError(f"{at}: fn must be a non-empty string, got {fn!r}")
            camera_id = lists["cam_id"][t][i]
            if isinstance(camera_id, bool) or not isinstance(camera_id, int):
                raise DatasetError(f"{at}: cam_id must be an integer, got {camera_id!r}")
            fx, fy, cx, cy = _intrinsics(lists["k"][t][i], at)
            w2c = check_rigid(lists["w2c"][t][i], "w2c")
            if isinstance(w2c, str):
                raise DatasetError(f"{at}: {w2c}")
            image = folder / "ims" / fn
            if not image.is_file():
                raise DatasetError(f"{at}: missing image {image}")
            mask: Path | None = None
            if masks:
                mask = (folder / "seg" / fn).with_suffix(".png")
                if not mask.is_file():
                    raise DatasetError(f"{at}: missing segmentation {mask}")
            try:
                camera = Camera(fx, fy, cx, cy, torch.from_numpy(w2c).float(), width, height)
            except ValueError as error:
                raise DatasetError(f"{at}: {error}") from None
            views.append(_View(t, camera_id, camera, image, mask))
    return _Meta(path, width, height, views, num_timesteps)


def _load_rgb(
    view: _View, meta: _Meta, background: tuple[float, float, float], factor: int
) -> UInt8[np.ndarray, "H W 3"]:
    image = read_image(view.image)
    height, width = image.shape[:2]
    if (width, height) != (meta.width, meta.height):
        raise DatasetError(
            f"{view.image}: image is {width}×{height} but {meta.path} gives "
            f"w={meta.width}, h={meta.height}"
        )
    if image.shape[2] == 4:
        image = composite(image, background)
    return downscale(image, factor)


def _load_mask(view: _View, meta: _Meta, factor: int) -> UInt8[np.ndarray, "H W 1"]:
    assert view.mask is not None
    mask = cv2.imread(str(view.mask), cv2.IMREAD_GRAYSCALE)
    if mask is None or mask.size == 0:
        raise DatasetError(f"{view.mask}: cannot read image")
    height, width = mask.shape[:2]
    if (width, height) != (meta.width, meta.height):
        raise DatasetError(
            f"{view.mask}: segmentation is {width}×{height} but {meta.path} gives "
            f"w={meta.width}, h={meta.height}"
        )
    if mask.max() <= 1:  # saved as 0/1 labels (the bilevel PNGs of the released data)
        mask = mask * np.uint8(255)
    return downscale(mask[:, :, None], factor)


def _split(
    meta: _Meta,
    denominator: int,
    background: tuple[float, float, float],
    factor: int,
    cache_bytes: int,
) -> Split:
    views = meta.views
    size = downscaled_size(meta.width, meta.height, factor)
    sizes = [(size[1], size[0])] * len(views)
    scale = 1.0 / factor
    cameras = [v.camera.scaled(scale) if factor > 1 else v.camera for v in views]
    times = torch.tensor([v.timestep / denominator for v in views], dtype=torch.float32)
    masks = None
    if views[0].mask is not None:
        # A mask is a third of its RGB image's bytes: a quarter of the budget.
        masks = LazyImages(lambda i: _load_mask(views[i], meta, factor), sizes, 1, cache_bytes // 4)
        cache_bytes -= cache_bytes // 4
    images = LazyImages(
        lambda i: _load_rgb(views[i], meta, background, factor), sizes, 3, cache_bytes
    )
    return Split(cameras, times, images, masks, [v.image for v in views])


def read_point_cloud_npz(
    path: Path,
) -> tuple[Float[torch.Tensor, "P 3"], Float[torch.Tensor, "P 3"]]:
    """Positions and colours in [0, 1] of an `init_pt_cld.npz` (rows x, y, z, r, g, b, …)."""
    if not zipfile.is_zipfile(path):
        raise DatasetError(f"{path}: not an .npz archive (not a zip file)")
    try:
        archive = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
        problem = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise DatasetError(f"{path}: not a readable .npz archive ({problem})") from None
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise DatasetError(f"{path}: not an .npz archive")
    with archive:
        if "data" not in archive.files:
            raise DatasetError(f"{path}: no array 'data' (found {', '.join(archive.files)})")
        try:
            data = np.asarray(archive["data"], dtype=np.float64)
        except (OSError, ValueError, TypeError, zipfile.BadZipFile) as error:
            problem = str(error).splitlines()[0] if str(error) else type(error).__name__
            raise DatasetError(f"{path}: cannot read array 'data' ({problem})") from None
    if data.ndim != 2 or data.shape[1] < 6:
        raise DatasetError(
            f"{path}: 'data' must be [P, ≥6] (x, y, z, r, g, b, …), got {list(data.shape)}"
        )
    data = data[np.isfinite(data[:, :6]).all(axis=1)]
    if len(data) == 0:
        raise DatasetError(f"{path}: no point with finite coordinates and colour")
    rgb = data[:, 3:6]
    if rgb.max() > 1.0 + 1e-6:  # stored as 0–255
        rgb = rgb / 255.0
    points = torch.from_numpy(data[:, :3]).float()
    return points, torch.from_numpy(np.clip(rgb, 0.0, 1.0)).float()


def _check_first_images(metas: dict[str, _Meta], background: tuple[float, float, float]) -> None:
    """Decode one image (and mask) per camera now, so a wrong size fails before training."""
    firsts: dict[tuple[str, int], tuple[_View, _Meta]] = {}
    for meta in metas.values():
        for view in meta.views:
            firsts.setdefault((str(meta.path), view.camera_id), (view, meta))
    with progress_bar() as progress:
        task = progress.add_task("checking panoptic cameras", total=len(firsts))
        for view, meta in firsts.values():
            _load_rgb(view, meta, background, 1)
            if view.mask is not None:
                _load_mask(view, meta, 1)
            progress.advance(task)


def parse_panoptic(
    path: Path,
    downscale: int = 1,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    num_random_points: int = 20_000,
    seed: int = 0,
    cache_bytes: int = HOST_CACHE_BYTES,
) -> SceneData:
    """Read a Dynamic 3D Gaussians (Panoptic) folder; see the module docstring."""
    path = capture_folder(path, downscale)
    masks = (path / "seg").is_dir()
    metas: dict[str, _Meta] = {}
    for split, name in META_FILES.items():
        if not (path / name).is_file():
            raise DatasetError(f"{path / name}: missing (a Panoptic folder needs it)")
        metas[split] = _read_meta(path, path / name, masks)
    _check_first_images(metas, background)
    denominator = max(max(m.num_timesteps for m in metas.values()) - 1, 1)
    budgets = {"train": cache_bytes - cache_bytes // 4, "test": cache_bytes // 4}
    splits = {
        name: _split(meta, denominator, background, downscale, budgets[name])
        for name, meta in metas.items()
    }

    points: torch.Tensor | None = None
    colors: torch.Tensor | None = None
    if (path / POINT_CLOUD).is_file():
        points, colors = read_point_cloud_npz(path / POINT_CLOUD)
    train_cameras = splits["train"].cameras
    box = scene_box_from_cameras(train_cameras, points)
    if points is None:
        depths = depth_ranges_around_box(train_cameras, box)
        points = points_in_common_view(train_cameras, depths, num_random_points, seed)
    return SceneData(
        name=path.resolve().name,
        train=splits["train"],
        val=splits["test"],
        test=splits["test"],
        scene_box=box,
        points=points,
        point_colors=colors,
        background=torch.tensor(background, dtype=torch.float32),
    )

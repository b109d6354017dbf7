"""The Panoptic-sports layout of Dynamic 3D Gaussians (Luiten et al. 2024).

Files, as that project's `train.py` reads them:

- `train_meta.json`, `test_meta.json`: `w`, `h` (image size in pixels) and four nested
  lists indexed [timestep t][view i]: `k` (3×3 pinhole intrinsics, pixel centres at
  +0.5 as in every 3DGS rasterizer; per frame, so they may change), `w2c` (4×4
  world-to-camera, OpenCV axes), `fn` (image path relative to `ims/`, e.g.
  "0/000000.jpg"; when that file is missing, the same name as .jpg, .jpeg or .png is
  used) and `cam_id` (which fixed camera took it).
- `ims/<fn>`: the RGB frames.
- `seg/<fn with .png>` (optional, and possibly for some cameras only): foreground
  segmentation, 0/1 or 0/255. It becomes the split's masks ("segmentation": the
  foreground, not where anything is). A frame without one counts fully in a masked loss.
- `init_pt_cld.npz` (optional): array `data`, one row per point: x, y, z, r, g, b
  (colours in [0, 1]; 0–255 is recognised and rescaled), segmentation.

Times: timestep t of T becomes t / (T − 1); train and test share the denominator (the
larger T of the two files), so equal timesteps get equal times. The test split is
`test_meta.json`, and validation uses it too. Public releases often ship only
`train_meta.json`: then `--holdout` decides which views are held out for evaluation
(`hold_out`), and the run says which. Without a point cloud the initial points are
uniform in the volume every train camera sees, between depths bounding the scene box
the cameras imply (`points_in_common_view`), until `dyngs.datamanagers.init_points`
finds better ones in the images.

Images are read lazily (JPEG decode and downscale on first use; the uint8 frames kept
in memory total at most `cache_bytes`, three quarters of it for the train split). Every
problem with the input raises a one-line DatasetError naming the file.

Letters: T timesteps, C views per timestep, H×W image, P points.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from jaxtyping import Float, UInt8
from rich.markup import escape

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
    mirror_world,
    points_in_common_view,
    scene_box_from_cameras,
    share_ahead,
)
from dyngs.datamanagers.files import array, load_json, require, whole
from dyngs.datamanagers.images import composite, downscale, downscaled_size, read_image
from dyngs.datamanagers.progress import progress_bar, report
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


_RawView = tuple[str, int, int, tuple[float, float, float, float], np.ndarray, Path, Path | None]
"""(where, timestep, camera id, (fx, fy, cx, cy), w2c as the file gives it, image, mask)."""


@dataclass(frozen=True)
class _RawMeta:
    path: Path
    width: int
    height: int
    views: list[_RawView]
    num_timesteps: int


@dataclass(frozen=True)
class _Meta:
    path: Path
    width: int
    height: int
    views: list[_View]
    num_timesteps: int
    mirrored: bool = False
    """Every w2c was a reflection: the world was mirrored in x (`mirror_world`)."""
    inverted: bool = False
    """The file's w2c were camera-to-world matrices, and were inverted (`_inverted`)."""


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


def _read_meta(folder: Path, path: Path, masks: bool) -> _RawMeta:
    """A meta file's views, checked, with their `w2c` as the file gives them."""
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
    raw: list[_RawView] = []
    for t in range(num_timesteps):
        count = len(lists["fn"][t])
        for key in _KEYS:
            if len(lists[key][t]) != count:
                raise DatasetError(
                    f"{where}: {key}[{t}] has {len(lists[key][t])} views but fn[{t}] has {count}"
                )
        for i in range(count):
            raw.append((f"{where}: [{t}][{i}]", t, *_read_view(lists, t, i, where, folder, masks)))
    return _RawMeta(path, width, height, raw, num_timesteps)


def _build_meta(raw: _RawMeta, inverted: bool, mirrored: bool) -> _Meta:
    """The views of a meta file with their cameras, the capture's `w2c` read as
    camera-to-world (`inverted`) and in a mirrored world (`mirrored`) where it needs."""
    views: list[_View] = []
    for at, t, camera_id, intrinsics, w2c, image, mask in raw.views:
        pose = np.linalg.inv(w2c) if inverted else w2c
        pose = mirror_world(pose) if mirrored else pose
        try:
            camera = Camera(*intrinsics, torch.from_numpy(pose).float(), raw.width, raw.height)
        except ValueError as error:
            raise DatasetError(f"{at}: {error}") from None
        views.append(_View(t, camera_id, camera, image, mask))
    return _Meta(raw.path, raw.width, raw.height, views, raw.num_timesteps, mirrored, inverted)


def _read_view(
    lists: dict[str, list[list[Any]]], t: int, i: int, where: str, folder: Path, masks: bool
) -> tuple[int, tuple[float, float, float, float], np.ndarray, Path, Path | None]:
    """View [t][i] of a meta file, checked: camera id, intrinsics, w2c (a rotation or a
    reflection), image and mask paths."""
    at = f"{where}: [{t}][{i}]"
    fn = lists["fn"][t][i]
    if not isinstance(fn, str) or not fn:
        raise DatasetError(f"{at}: fn must be a non-empty string, got {fn!r}")
    camera_id = lists["cam_id"][t][i]
    if isinstance(camera_id, bool) or not isinstance(camera_id, int):
        raise DatasetError(f"{at}: cam_id must be an integer, got {camera_id!r}")
    intrinsics = _intrinsics(lists["k"][t][i], at)
    w2c = check_rigid(lists["w2c"][t][i], "w2c", allow_reflection=True)
    if isinstance(w2c, str):
        raise DatasetError(f"{at}: {w2c}")
    image = _find_image(folder / "ims" / fn)
    if image is None:
        raise DatasetError(
            f"{at}: missing image {folder / 'ims' / fn} (also tried .jpg, .jpeg, .png)"
        )
    mask: Path | None = None
    if masks:
        candidate = (folder / "seg" / fn).with_suffix(".png")
        mask = candidate if candidate.is_file() else None
    return camera_id, intrinsics, w2c, image, mask


def _inverted(
    raw: list[_RawView],
) -> bool:
    """Whether the file's `w2c` are camera-to-world matrices: read as given, the cameras
    look away from each other (the point nearest their optical axes lies behind most of
    them), and inverted they look at one scene. A release that mislabels its poses so is
    read as it means; a rig that truly looks outward is left alone."""
    given = [entry[4] for entry in raw]
    ahead = share_ahead(given)
    return ahead < 0.5 and share_ahead([np.linalg.inv(m) for m in given]) > ahead


def _mirrored(places: list[str], poses: list[np.ndarray]) -> bool:
    """Whether every camera is a reflection (a mirrored world frame, as in some public
    releases); a capture that mixes reflections and rotations cannot be one scene."""
    reflected = [np.linalg.det(pose[:3, :3]) < 0 for pose in poses]
    if any(reflected) and not all(reflected):
        first, proper = reflected.index(True), reflected.index(False)
        raise DatasetError(
            f"{places[first]}: w2c is a reflection (det −1) but {places[proper]} is a "
            "rotation: the cameras disagree on the world's handedness"
        )
    return any(reflected)


IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".JPG", ".JPEG", ".PNG")


def _find_image(path: Path) -> Path | None:
    """`path`, or the same name with another image suffix (a release may ship PNG where
    its metadata says JPEG, or the reverse)."""
    if path.is_file():
        return path
    for suffix in IMAGE_SUFFIXES:
        other = path.with_suffix(suffix)
        if other.is_file():
            return other
    return None


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
    if view.mask is None:  # this camera has no segmentation: every pixel counts
        height, width = downscaled_size(meta.width, meta.height, factor)[::-1]
        return np.full((height, width, 1), 255, dtype=np.uint8)
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
    known = [v.mask is not None for v in views]
    if any(known):
        # A mask is a third of its RGB image's bytes: a quarter of the budget.
        masks = LazyImages(lambda i: _load_mask(views[i], meta, factor), sizes, 1, cache_bytes // 4)
        cache_bytes -= cache_bytes // 4
    images = LazyImages(
        lambda i: _load_rgb(views[i], meta, background, factor), sizes, 3, cache_bytes
    )
    return Split(
        cameras,
        times,
        images,
        masks,
        [v.image for v in views],
        mask_kind="segmentation",
        mask_known=None if all(known) else known,
    )


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


HOLDOUT_EVERY = 10
"""`--holdout auto` on a capture of fewer than four cameras: every this many timesteps."""

HOLDOUT_MIN_CAMERAS = 4
"""`--holdout auto` holds out a whole camera from this many cameras up; with fewer, the
rest could not see what it sees from anywhere near, and a time step is held out instead."""


def hold_out(meta: _Meta, rule: str) -> tuple[_Meta, _Meta, str]:
    """Train and test views of a capture that has no `test_meta.json`, by `rule`:

    - `camera:ID`: every view of camera ID is a test view (a novel viewpoint);
    - `camera`: the camera nearest the centroid of all camera centres (the view the
      others surround most closely);
    - `every:N`: every view at timesteps t with t mod N = ⌊N / 2⌋ (novel times, seen by
      every camera; the first and last timesteps stay in training);
    - `auto`: `camera` with at least `HOLDOUT_MIN_CAMERAS` cameras, else
      `every:HOLDOUT_EVERY`.

    Returns both splits and one line saying what was held out.
    """
    cameras: dict[int, list[_View]] = {}
    for view in meta.views:
        cameras.setdefault(view.camera_id, []).append(view)
    if rule == "auto":
        rule = "camera" if len(cameras) >= HOLDOUT_MIN_CAMERAS else f"every:{HOLDOUT_EVERY}"
    if rule == "camera":
        centres = {i: v[0].camera.center.double() for i, v in cameras.items()}
        mean = torch.stack(list(centres.values())).mean(0)
        nearest = min(centres, key=lambda i: float((centres[i] - mean).norm()))
        rule = f"camera:{nearest}"
    kind, _, value = rule.partition(":")
    if kind == "camera":
        chosen = int(value)
        if chosen not in cameras:
            raise DatasetError(
                f"{meta.path}: --holdout {rule}: no camera {chosen} (cameras: "
                f"{', '.join(map(str, sorted(cameras)))})"
            )
        test = [v for v in meta.views if v.camera_id == chosen]
        said = f"camera {chosen} ({len(test)} views; {len(cameras) - 1} cameras train)"
    else:
        every = int(value)
        test = [v for v in meta.views if v.timestep % every == every // 2]
        steps = len({v.timestep for v in test})
        said = f"every {every}th timestep ({steps} of {meta.num_timesteps}, all cameras)"
    held = {id(v) for v in test}
    train = [v for v in meta.views if id(v) not in held]
    if not train or not test:
        raise DatasetError(f"{meta.path}: --holdout {rule} leaves an empty split")
    line = f"no test_meta.json: holding out {said} for evaluation (--holdout {rule})"
    return replace(meta, views=train), replace(meta, views=test), line


def _read_metas(path: Path, masks: bool, holdout: str) -> dict[str, _Meta]:
    """The train and test views of a capture: its meta files read, its `w2c` decided for
    all its cameras together (camera-to-world? a mirrored world?), and test views held out
    by `holdout` where it has no test_meta.json."""
    train_meta = path / META_FILES["train"]
    if not train_meta.is_file():
        raise DatasetError(f"{train_meta}: missing (a Panoptic folder needs it)")
    raws = {"train": _read_meta(path, train_meta, masks)}
    if (path / META_FILES["test"]).is_file():
        raws["test"] = _read_meta(path, path / META_FILES["test"], masks)
    every = [view for raw in raws.values() for view in raw.views]
    inverted = _inverted(every)
    poses = [np.linalg.inv(v[4]) if inverted else v[4] for v in every]
    mirrored = _mirrored([v[0] for v in every], poses)
    if inverted:
        report(escape(
            f"[panoptic] the w2c of {path.name} are camera-to-world matrices (read as given, "
            "the cameras would look away from each other): inverted"
        ))  # fmt: skip
    if mirrored:
        report(escape(
            f"[panoptic] every w2c of {path.name} is a reflection (det −1): the world is "
            "mirrored in x, so that each camera is a rotation (same pictures)"
        ))  # fmt: skip
    metas = {name: _build_meta(raw, inverted, mirrored) for name, raw in raws.items()}
    if "test" not in metas:
        metas["train"], metas["test"], line = hold_out(metas["train"], holdout)
        report(escape(f"[panoptic] {line}"))
    return metas


def parse_panoptic(
    path: Path,
    downscale: int = 1,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    num_random_points: int = 20_000,
    seed: int = 0,
    cache_bytes: int = HOST_CACHE_BYTES,
    holdout: str = "auto",
) -> SceneData:
    """Read a Dynamic 3D Gaussians (Panoptic) folder; see the module docstring."""
    path = capture_folder(path, downscale)
    masks = (path / "seg").is_dir()
    metas = _read_metas(path, masks, holdout)
    _check_first_images(metas, background)
    denominator = max(max(m.num_timesteps for m in metas.values()) - 1, 1)
    budgets = {"train": cache_bytes - cache_bytes // 4, "test": cache_bytes // 4}
    splits = {
        name: _split(meta, denominator, background, downscale, budgets[name])
        for name, meta in metas.items()
    }

    points: torch.Tensor | None = None
    colors: torch.Tensor | None = None
    source = "random in the cameras' common view"
    if (path / POINT_CLOUD).is_file():
        points, colors = read_point_cloud_npz(path / POINT_CLOUD)
        source = POINT_CLOUD
        if metas["train"].mirrored:
            points = points * torch.tensor([-1.0, 1.0, 1.0])
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
        points_source=source,
    )

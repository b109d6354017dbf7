"""The DyNeRF / Neural 3D Video layout (Li et al. 2022): synchronised videos plus LLFF poses.

Files:

- `poses_bounds.npy`: float [N, 17], row n for the n-th video in camera-number order.
  The first 15 numbers are a 3×5 matrix, row-major: columns one to three are the
  camera's down, right and backward axes in world space, column four its centre (the
  LLFF camera-to-world of Mildenhall et al. 2019), column five (H, W, focal) in pixels.
  The last two are the near and far depth bounds of the scene for that camera.
- `cam00.mp4`, `cam01.mp4`, …: one video per camera, all with the same frame count.
- `points3d.ply` or `fused.ply` (optional): initial points, as for D-NeRF.

Conventions:

- Axes: OpenCV's x (right) is LLFF's second column, y (down) its first, z (forward)
  the negated third (`llff_to_world_to_camera`).
- Intrinsics: fx = fy = focal, principal point at the image centre (W/2, H/2), both
  scaled to the size the video actually has (N3DV's videos are 2704×2028, as its poses).
- Splits: `cam00` is the test view (the N3DV convention; the lowest-numbered camera when
  there is no cam00) and validation uses it too; the other cameras at every frame train.
- Times: frame f of F becomes f / (F − 1).
- Initial points: the point cloud when there is one, else uniform in the volume every
  train camera sees between its near and far bound.

Frames: each video is decoded once with OpenCV, downscaled by `downscale` as it is read,
and appended as raw uint8 to `<video>-x<downscale>.u8` in a cache folder, beside a JSON
sidecar recording the source's size and modification time (a changed video is decoded
again). The folder is `$DYNGS_CACHE/frames-<scene>-<hash>/` when DYNGS_CACHE is set,
else `<dataset>/.dyngs-cache/`, else (a read-only dataset) `~/.cache/dyngs/...`. Training
memory-maps these files and copies out one frame at a time: no step holds every frame,
and none holds them as float.

Every problem with the input raises a one-line DatasetError naming the file.

Letters: N cameras, F frames, H×W image, P points.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from jaxtyping import UInt8
from rich.progress import Progress, TaskID

from dyngs.datamanagers.base import (
    HOST_CACHE_BYTES,
    LazyImages,
    SceneData,
    Split,
    capture_folder,
)
from dyngs.datamanagers.cameras import (
    check_rigid,
    llff_to_world_to_camera,
    points_in_common_view,
    scene_box_from_cameras,
)
from dyngs.datamanagers.dnerf import find_point_cloud, read_point_cloud
from dyngs.datamanagers.files import load_npy
from dyngs.datamanagers.images import downscale, downscaled_size
from dyngs.datamanagers.procedural import cache_dir
from dyngs.datamanagers.progress import progress_bar
from dyngs.errors import DatasetError
from dyngs.types import Camera

POSES = "poses_bounds.npy"
CACHE_VERSION = 1
"""Part of every sidecar: bump it whenever the cached frames change."""
_VIDEO = re.compile(r"cam(\d+)\.mp4")
ASPECT_TOLERANCE = 0.01
"""Largest relative difference between the x and y scale from pose size to video size."""


@dataclass(frozen=True)
class _Pose:
    camera: Camera
    """At the video's full frame size."""
    near: float
    far: float


@dataclass
class FrameCache:
    """One video's decoded, downscaled frames: raw uint8 [F, H, W, 3] in `path`."""

    video: Path
    path: Path
    frames: int
    height: int
    width: int
    full_width: int
    full_height: int
    _map: np.memmap | None = None

    def frame(self, index: int) -> UInt8[np.ndarray, "H W 3"]:
        """A copy of frame `index` (the memory map stays; the page cache holds the rest)."""
        if self._map is None:
            shape = (self.frames, self.height, self.width, 3)
            try:
                self._map = np.memmap(self.path, dtype=np.uint8, mode="r", shape=shape)
            except (OSError, ValueError) as error:
                raise DatasetError(f"{self.path}: cannot map the frame cache ({error})") from None
        return np.array(self._map[index])


def _videos(folder: Path) -> list[Path]:
    """camNN.mp4 in camera-number order."""
    found = []
    for path in folder.iterdir():
        match = _VIDEO.fullmatch(path.name)
        if match and path.is_file():
            found.append((int(match.group(1)), path))
    return [path for _, path in sorted(found)]


def _cache_folder(folder: Path) -> Path:
    resolved = folder.resolve()
    digest = hashlib.sha256(str(resolved).encode()).hexdigest()[:10]
    shared = cache_dir() / f"frames-{resolved.name}-{digest}"
    if os.environ.get("DYNGS_CACHE"):
        candidates = [shared]
    else:
        candidates = [folder / ".dyngs-cache", shared]
    for candidate in candidates:
        try:
            candidate.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(candidate, os.W_OK):
            return candidate
    raise DatasetError(f"{candidates[-1]}: cannot create the frame cache folder")


def _source_stamp(video: Path) -> dict[str, int]:
    stat = video.stat()
    return {"source_bytes": stat.st_size, "source_mtime_ns": stat.st_mtime_ns}


def _cached(video: Path, raw: Path, factor: int) -> FrameCache | None:
    """The cache of `video` if it is complete and made from the current file."""
    sidecar = raw.with_suffix(".json")
    try:
        meta = json.loads(sidecar.read_text())
        expected = {"version": CACHE_VERSION, "downscale": factor, **_source_stamp(video)}
        if any(meta.get(key) != value for key, value in expected.items()):
            return None
        cache = FrameCache(
            video,
            raw,
            int(meta["frames"]),
            int(meta["height"]),
            int(meta["width"]),
            int(meta["full_width"]),
            int(meta["full_height"]),
        )
        complete = raw.stat().st_size == cache.frames * cache.height * cache.width * 3
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return cache if complete else None


def _decode(video: Path, raw: Path, factor: int, progress: Progress, task: TaskID) -> FrameCache:
    """Decode `video` into `raw` frame by frame (written to a temporary name, then renamed,
    so an interrupted decode leaves no half cache behind)."""
    capture = cv2.VideoCapture(str(video))
    if not capture.isOpened():
        raise DatasetError(f"{video}: cannot open the video (not a format OpenCV decodes)")
    partial = raw.with_name(f"{raw.name}.{os.getpid()}.partial")
    full: tuple[int, int] | None = None
    count = 0
    try:
        with partial.open("wb") as out:
            while True:
                ok, frame = capture.read()
                if not ok:
                    break
                size = (frame.shape[1], frame.shape[0])
                if full is None:
                    full = size
                elif size != full:
                    raise DatasetError(
                        f"{video}: frame {count} is {size[0]}×{size[1]}, "
                        f"frame 0 is {full[0]}×{full[1]}"
                    )
                rgb = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
                out.write(np.ascontiguousarray(downscale(rgb, factor)).tobytes())
                count += 1
                progress.advance(task)
        if full is None:
            raise DatasetError(f"{video}: no frame could be decoded")
        os.replace(partial, raw)
    finally:
        capture.release()
        partial.unlink(missing_ok=True)
    width, height = downscaled_size(*full, factor)
    meta = {
        "version": CACHE_VERSION,
        "downscale": factor,
        **_source_stamp(video),
        "frames": count,
        "height": height,
        "width": width,
        "full_width": full[0],
        "full_height": full[1],
    }
    sidecar = raw.with_suffix(".json")
    staged = sidecar.with_name(f"{sidecar.name}.{os.getpid()}.partial")
    staged.write_text(json.dumps(meta))
    os.replace(staged, sidecar)
    return FrameCache(video, raw, count, height, width, full[0], full[1])


def decode_videos(videos: list[Path], folder: Path, factor: int) -> list[FrameCache]:
    """Each video's frame cache, decoding (in threads) those not cached yet."""
    cache_folder = _cache_folder(folder)
    raws = [cache_folder / f"{video.stem}-x{factor}.u8" for video in videos]
    caches: list[FrameCache | None] = [
        _cached(video, raw, factor) for video, raw in zip(videos, raws, strict=True)
    ]
    todo = [i for i, cache in enumerate(caches) if cache is None]
    if todo:
        estimate = 0
        for i in todo:
            capture = cv2.VideoCapture(str(videos[i]))
            estimate += max(int(capture.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
            capture.release()
        pool = ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1, len(todo)))
        try:
            with progress_bar() as progress:
                task = progress.add_task(f"decoding {len(todo)} videos", total=estimate or None)
                jobs = {
                    i: pool.submit(_decode, videos[i], raws[i], factor, progress, task)
                    for i in todo
                }
                for i, job in jobs.items():
                    caches[i] = job.result()
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
    return [cache for cache in caches if cache is not None]


def _read_poses(path: Path, videos: list[Path]) -> list[_Pose]:
    """Check poses_bounds.npy against the videos; cameras at the pose's H×W."""
    data = load_npy(path)
    if data.ndim != 2 or data.shape[1] != 17 or data.dtype.kind not in "fiu":
        raise DatasetError(
            f"{path}: need a float array [cameras, 17], got {data.dtype} {list(data.shape)}"
        )
    if len(data) != len(videos):
        names = ", ".join(v.name for v in videos) or "none"
        raise DatasetError(
            f"{path}: {len(data)} camera rows but {len(videos)} camNN.mp4 videos ({names})"
        )
    poses: list[_Pose] = []
    for row, video in zip(data.astype(np.float64), videos, strict=True):
        where = f"{path}: row {len(poses)} ({video.name})"
        if not np.isfinite(row).all():
            raise DatasetError(f"{where}: non-finite entries")
        matrix = row[:15].reshape(3, 5)
        height, width, focal = matrix[:, 4]
        near, far = row[15:17]
        if height < 1 or width < 1 or focal <= 0:
            raise DatasetError(
                f"{where}: H, W, focal must be positive, got {height}, {width}, {focal}"
            )
        if not 0 < near < far:
            raise DatasetError(f"{where}: bounds need 0 < near < far, got {near}, {far}")
        c2w = np.eye(4)
        c2w[:3] = matrix[:, :4]
        checked = check_rigid(c2w, "pose")
        if isinstance(checked, str):
            raise DatasetError(f"{where}: {checked}")
        w2c = torch.from_numpy(llff_to_world_to_camera(matrix[:, :4])).float()
        camera = Camera(focal, focal, width / 2, height / 2, w2c, round(width), round(height))
        poses.append(_Pose(camera, float(near), float(far)))
    return poses


def _at_video_size(pose: _Pose, cache: FrameCache, poses_path: Path) -> Camera:
    """The pose's camera for the video's actual full frame size."""
    camera = pose.camera
    sx = cache.full_width / camera.width
    sy = cache.full_height / camera.height
    if abs(sx / sy - 1.0) > ASPECT_TOLERANCE:
        raise DatasetError(
            f"{cache.video}: frames are {cache.full_width}×{cache.full_height} but "
            f"{poses_path} gives {camera.width}×{camera.height} (another aspect ratio)"
        )
    return Camera(
        camera.fx * sx,
        camera.fy * sy,
        camera.cx * sx,
        camera.cy * sy,
        camera.world_to_camera,
        cache.full_width,
        cache.full_height,
    )


def _split(caches: list[FrameCache], cameras: list[Camera], frames: int, cache_bytes: int) -> Split:
    """Every frame of every camera, time-major."""
    views = [(c, f) for f in range(frames) for c in range(len(caches))]
    sizes = [(caches[c].height, caches[c].width) for c, _ in views]
    denominator = max(frames - 1, 1)
    return Split(
        cameras=[cameras[c] for c, _ in views],
        times=torch.tensor([f / denominator for _, f in views], dtype=torch.float32),
        images=LazyImages(lambda i: caches[views[i][0]].frame(views[i][1]), sizes, 3, cache_bytes),
    )


def _common_frame_count(caches: list[FrameCache]) -> int:
    """The frame count every video shares; a DatasetError naming one that differs."""
    longest = max(caches, key=lambda c: c.frames)
    for cache in caches:
        if cache.frames != longest.frames:
            raise DatasetError(
                f"{cache.video}: {cache.frames} frames, but {longest.video.name} has "
                f"{longest.frames} (every video needs the same number)"
            )
    return longest.frames


def parse_dynerf(
    path: Path,
    downscale: int = 1,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    num_random_points: int = 20_000,
    seed: int = 0,
    cache_bytes: int = HOST_CACHE_BYTES,
) -> SceneData:
    """Read a DyNeRF / N3DV folder; see the module docstring."""
    path = capture_folder(path, downscale)
    poses_path = path / POSES
    if not poses_path.is_file():
        raise DatasetError(f"{poses_path}: missing (a DyNeRF folder needs it)")
    videos = _videos(path)
    if len(videos) < 2:
        raise DatasetError(
            f"{path}: need at least two camNN.mp4 videos (one to test, one to train), "
            f"found {len(videos)}"
        )
    poses = _read_poses(poses_path, videos)  # before decoding: bad poses fail fast
    caches = decode_videos(videos, path, downscale)
    frames = _common_frame_count(caches)
    cameras = []
    for pose, cache in zip(poses, caches, strict=True):
        camera = _at_video_size(pose, cache, poses_path)
        cameras.append(camera.scaled(1.0 / downscale) if downscale > 1 else camera)
    test_index = next((i for i, v in enumerate(videos) if v.stem == "cam00"), 0)
    train_index = [i for i in range(len(videos)) if i != test_index]
    # Three quarters of the host cache for the train split, a quarter for the test view.
    train_caches = [caches[i] for i in train_index]
    train_bytes = cache_bytes - cache_bytes // 4
    train = _split(train_caches, [cameras[i] for i in train_index], frames, train_bytes)
    test = _split([caches[test_index]], [cameras[test_index]], frames, cache_bytes // 4)

    points: torch.Tensor | None = None
    colors: torch.Tensor | None = None
    cloud = find_point_cloud(path)
    source = "random in the cameras' common view"
    if cloud is not None:
        points, colors = read_point_cloud(cloud)
        source = cloud.name
    else:
        train_cameras = [cameras[i] for i in train_index]
        depths = [(poses[i].near, poses[i].far) for i in train_index]
        points = points_in_common_view(train_cameras, depths, num_random_points, seed)
    box = scene_box_from_cameras([cameras[i] for i in train_index], points)
    return SceneData(
        name=path.resolve().name,
        train=train,
        val=test,
        test=test,
        scene_box=box,
        points=points,
        point_colors=colors,
        background=torch.tensor(background, dtype=torch.float32),
        points_source=source,
    )

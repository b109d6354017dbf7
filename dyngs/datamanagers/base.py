"""What a dataset parser yields, whatever the on-disk format.

Letters: F frames in a split, H×W image, C channels, P initial points.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import overload

import numpy as np
import torch
from jaxtyping import Float, UInt8
from torch import Tensor

from dyngs.errors import DatasetError
from dyngs.types import Camera, SceneBox

HOST_CACHE_BYTES = 1 << 30
"""Default bound on the decoded uint8 images a lazy split keeps in host memory."""


def capture_folder(path: Path | str, downscale: int) -> Path:
    """The checks every parser starts with: a positive downscale and an existing folder."""
    path = Path(path)
    if downscale < 1:
        raise ValueError(f"downscale must be a positive integer, got {downscale}")
    if not path.is_dir():
        raise DatasetError(f"{path}: not a directory")
    return path


class LazyImages(Sequence[UInt8[Tensor, "H W C"]]):
    """Frames read on demand and kept in a bounded least-recently-used uint8 cache.

    `load(i)` returns frame i as uint8 [H, W, C] numpy (reading, decoding, undistorting
    and downscaling as its format needs, raising a DatasetError that names the file when
    it cannot). `sizes[i]` is frame i's (height, width), known without reading it, so
    the datamanager can plan memory before any pixel is loaded. At most `cache_bytes`
    of decoded frames stay in memory; `loads` counts calls to `load`.
    """

    def __init__(
        self,
        load: Callable[[int], UInt8[np.ndarray, "H W C"]],
        sizes: Sequence[tuple[int, int]],
        channels: int = 3,
        cache_bytes: int = HOST_CACHE_BYTES,
    ) -> None:
        if cache_bytes < 0:
            raise ValueError(f"cache_bytes must be ≥ 0, got {cache_bytes}")
        self._load = load
        self._sizes = list(sizes)
        self.channels = channels
        self.cache_bytes = cache_bytes
        self.loads = 0
        self._cache: OrderedDict[int, Tensor] = OrderedDict()
        self._cached_bytes = 0
        # The datamanager may read ahead in a thread; the cache bookkeeping is shared.
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._sizes)

    def size(self, index: int) -> tuple[int, int]:
        """(height, width) of frame `index`, without reading it."""
        return self._sizes[index]

    @overload
    def __getitem__(self, index: int) -> UInt8[Tensor, "H W C"]: ...

    @overload
    def __getitem__(self, index: slice) -> list[UInt8[Tensor, "H W C"]]: ...

    def __getitem__(
        self, index: int | slice
    ) -> UInt8[Tensor, "H W C"] | list[UInt8[Tensor, "H W C"]]:
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        if not -len(self) <= index < len(self):
            raise IndexError(f"frame {index} out of range for {len(self)} frames")
        index %= len(self)
        with self._lock:
            cached = self._cache.get(index)
            if cached is not None:
                self._cache.move_to_end(index)
                return cached
        array = self._load(index)
        height, width = self._sizes[index]
        if array.dtype != np.uint8 or array.shape != (height, width, self.channels):
            raise ValueError(
                f"frame {index} loaded as {array.dtype} {array.shape}, expected uint8 "
                f"{(height, width, self.channels)}"
            )
        image = torch.from_numpy(np.ascontiguousarray(array))
        with self._lock:
            self.loads += 1
            nbytes = image.numel()
            if nbytes <= self.cache_bytes and index not in self._cache:
                self._cache[index] = image
                self._cached_bytes += nbytes
                while self._cached_bytes > self.cache_bytes:
                    _, dropped = self._cache.popitem(last=False)
                    self._cached_bytes -= dropped.numel()
        return image

    def clear(self) -> None:
        """Drop every cached frame."""
        with self._lock:
            self._cache.clear()
            self._cached_bytes = 0

    @property
    def cached_bytes(self) -> int:
        """Bytes of decoded frames held in memory now."""
        return self._cached_bytes


def image_size(images: Sequence[Tensor], index: int) -> tuple[int, int]:
    """(height, width) of frame `index`, without reading a lazy frame."""
    if isinstance(images, LazyImages):
        return images.size(index)
    height, width = images[index].shape[:2]
    return int(height), int(width)


@dataclass
class Split:
    """The frames of one split: a camera, a time in [0, 1] and an image each.

    Images are uint8 on the CPU (a quarter of float32's memory): a list held in memory,
    or `LazyImages` read from disk on demand for captures too large to hold. The
    datamanager converts them once, on the training device, when they fit, and per
    batch otherwise.
    """

    cameras: list[Camera]
    times: Float[Tensor, " F"]
    images: Sequence[UInt8[Tensor, "H W 3"]]
    masks: Sequence[UInt8[Tensor, "H W 1"]] | None = None
    """Per-pixel weights of the photometric loss (255 = fully counted): the alpha of
    RGBA sources, or a format's foreground segmentation."""
    paths: list[Path] | None = None
    mask_kind: str = "alpha"
    """What the masks mark: "alpha", where anything is (the alpha of RGBA sources: outside
    it is empty space), or "segmentation", a foreground (the background lies outside it)."""
    mask_known: list[bool] | None = None
    """Per frame, whether it has a mask of its own; a frame without one (all 255) counts
    fully in the loss and says nothing about where things are. None: every frame has."""

    def __len__(self) -> int:
        return len(self.cameras)

    def has_mask(self, index: int) -> bool:
        """Whether frame `index` has a mask of its own."""
        return self.masks is not None and (self.mask_known is None or self.mask_known[index])


@dataclass
class SceneData:
    name: str
    train: Split
    val: Split
    test: Split
    scene_box: SceneBox
    points: Float[Tensor, "P 3"]
    """Initial Gaussian centres (from a point cloud in the folder, or random in the box)."""
    point_colors: Float[Tensor, "P 3"] | None
    background: Float[Tensor, " 3"]
    """The colour RGBA images were composited over, in [0, 1]; renders use the same."""
    point_lifetimes: Float[Tensor, "P 2"] | None = None
    """Per point, (τ, σ) of the time it was seen around, for points of what moves (made
    from the images); σ = inf, or None for all, for points that exist at every time."""
    points_source: str = "random"
    """Where `points` came from: a file's name (a point cloud in the folder), or how they
    were made ("random in the box", "carved from 108 silhouettes", …)."""
    points_on_surfaces: bool = False
    """Whether the points are known to lie on what the images show: made from the images,
    or a file's cloud that `choose_initial_points` judged real. Random points and a cloud
    used unchecked (`--initial-points file`) are not."""

    @property
    def num_timestamps(self) -> int:
        return int(torch.unique(self.train.times).numel())

    def summary(self) -> str:
        """One line saying what was found: cameras, frames, resolution, time range."""
        splits = {"train": self.train, "val": self.val, "test": self.test}
        cameras: set[tuple[float, ...]] = set()
        sizes: set[tuple[int, int]] = set()
        for split in splits.values():
            for camera in split.cameras:
                pose = camera.world_to_camera.double().flatten().tolist()
                intrinsics = (camera.fx, camera.fy, camera.cx, camera.cy)
                cameras.add(tuple(round(v, 5) for v in (*pose, *intrinsics)))
                sizes.add((camera.width, camera.height))
        resolution = ", ".join(f"{w}×{h}" for w, h in sorted(sizes))
        times = torch.cat([s.times for s in splits.values() if len(s) > 0])
        counts = " / ".join(f"{len(split)} {name}" for name, split in splits.items())
        return (
            f"{self.name}: {len(cameras)} cameras, {self.num_timestamps} timestamps, "
            f"{counts} views, {resolution}, t ∈ [{float(times.min()):.3g}, "
            f"{float(times.max()):.3g}], {len(self.points):,} points ({self.points_source})"
        )

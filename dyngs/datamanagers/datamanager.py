"""Find and parse a dataset, then serve training batches and evaluation views.

Letters: H×W image.
"""

from __future__ import annotations

from bisect import bisect_left, bisect_right
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import torch
from jaxtyping import Float
from rich.markup import escape
from torch import Tensor

from dyngs.datamanagers.base import HOST_CACHE_BYTES, LazyImages, SceneData, Split, image_size
from dyngs.datamanagers.fixed_cameras import PIXEL_CHANGE, FixedCameras
from dyngs.datamanagers.formats import FORMATS
from dyngs.datamanagers.init_points import INITIAL_POINTS, choose_initial_points
from dyngs.datamanagers.procedural import demo_path
from dyngs.datamanagers.progress import report
from dyngs.errors import ConfigError, DatasetError
from dyngs.types import Camera

DEMO = "demo"
"""The `--data` value that selects the built-in procedural scene."""
AUTO = "auto"
"""The `--format` value that picks the format from the folder's contents."""


@dataclass(frozen=True)
class DataConfig:
    """How a dataset is loaded and served."""

    downscale: int = 1
    """Divide image width and height by this factor."""
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """RGB the RGBA images are composited over (and renders use)."""
    num_random_points: int = 20_000
    """Initial points made when the folder has no usable point cloud: carved from
    silhouettes or triangulated from the images where they allow, else uniform in the
    scene box (D-NeRF) or in the volume every train camera sees (Panoptic, DyNeRF,
    Nerfies)."""
    initial_points: str = "auto"
    """Where the Gaussians start: `auto` (the capture's point cloud when it is real, else
    points made from the images, else random; the run says which and why), `file` (the
    capture's cloud, whatever it looks like), `data` (made from the images), `random`."""
    device_cache_bytes: int = 2 << 30
    """Keep float images on the training device when they fit in this many bytes."""
    host_cache_bytes: int = HOST_CACHE_BYTES
    """Keep at most this many bytes of decoded uint8 frames in host memory for the
    formats read lazily (Panoptic, DyNeRF, Nerfies); the rest are re-read on demand."""
    format: str = AUTO
    """Dataset format: `auto` (from the folder's contents), `dnerf`, `panoptic`,
    `dynerf` or `nerfies`."""
    holdout: str = "auto"
    """Views held out for evaluation when a capture has no test split of its own (a
    Panoptic release with only train_meta.json): `camera:ID` (a novel viewpoint), `camera`
    (the one nearest the others' centroid), `every:N` (every N-th timestep, all cameras:
    novel times), or `auto` (`camera` from four cameras up, else `every:10`)."""

    def __post_init__(self) -> None:
        if self.downscale < 1:
            raise ConfigError(f"--downscale must be ≥ 1, got {self.downscale}")
        if len(self.background) != 3 or not all(0.0 <= c <= 1.0 for c in self.background):
            raise ConfigError(f"--background must be three values in [0, 1], got {self.background}")
        if self.num_random_points < 1:
            raise ConfigError(f"--num-random-points must be ≥ 1, got {self.num_random_points}")
        if self.device_cache_bytes < 0:
            raise ConfigError(f"--device-cache-bytes must be ≥ 0, got {self.device_cache_bytes}")
        if self.host_cache_bytes < 0:
            raise ConfigError(f"--host-cache-bytes must be ≥ 0, got {self.host_cache_bytes}")
        if not _valid_holdout(self.holdout):
            raise ConfigError(
                f"--holdout must be auto, camera, camera:ID or every:N (N ≥ 2), "
                f"got {self.holdout!r}"
            )
        if self.initial_points not in INITIAL_POINTS:
            raise ConfigError(
                f"--initial-points must be one of {', '.join(INITIAL_POINTS)}, "
                f"got {self.initial_points!r}"
            )
        names = [AUTO, *FORMATS.names()]
        if self.format not in names:
            raise ConfigError(f"--format must be one of {', '.join(names)}, got {self.format!r}")


def _valid_holdout(rule: str) -> bool:
    kind, colon, value = rule.partition(":")
    if not colon:
        return rule in ("auto", "camera")
    if kind == "camera":
        return value.lstrip("-").isdigit()
    return kind == "every" and value.isdigit() and int(value) >= 2


def load_scene(data: str | Path, config: DataConfig, seed: int = 0) -> SceneData:
    """Parse `data`: "demo" (the built-in procedural scene) or a dataset folder, in the
    format `config.format` names or, for "auto", the first whose marker file it holds.

    `seed` seeds the random initial points of folders that have no point cloud. One line
    on stderr says what was found.
    """
    if str(data) == DEMO:
        scene = FORMATS.get("dnerf").parse(demo_path(), config, seed)
        return _with_initial_points("dnerf", scene, config, seed)
    path = Path(data).expanduser()
    if not path.exists():
        raise DatasetError(f"{path}: does not exist")
    if not path.is_dir():
        raise DatasetError(f"{path}: not a directory")
    if config.format == AUTO:
        found = [entry for entry in FORMATS if (path / entry.item.marker).is_file()]
        if not found:
            expected = " or ".join(entry.item.marker for entry in FORMATS)
            raise DatasetError(
                f"{path}: not a dataset folder (expected {expected} in it, or '{DEMO}')"
            )
        name, fmt = found[0].name, found[0].item
    else:
        name, fmt = config.format, FORMATS.get(config.format)
    return _with_initial_points(name, fmt.parse(path, config, seed), config, seed)


def _with_initial_points(name: str, scene: SceneData, config: DataConfig, seed: int) -> SceneData:
    """The parsed scene with its initial points chosen (`choose_initial_points`); two
    lines on stderr say what was found and where the Gaussians start."""
    report(f"[bold]{name}[/bold] {scene.summary()}")
    scene, line = choose_initial_points(
        scene, config.initial_points, config.num_random_points, PIXEL_CHANGE, seed
    )
    report(escape(f"[points] {line}"))
    return scene


@dataclass
class TrainBatch:
    """One view: its camera and time, the image (float32 in [0, 1], on the device)."""

    camera: Camera
    time: float
    image: Float[Tensor, "H W 3"]
    mask: Float[Tensor, "H W 1"] | None
    """Per-pixel loss weights in [0, 1], when the split has masks (the alpha of RGBA
    sources, or a format's foreground segmentation)."""
    index: int
    """Position of the view in its split."""


class _ServedSplit:
    """A split's cameras on the device and its images either as float32 on the device
    (converted once) or as uint8 on the CPU (converted per batch). Lazy uint8 images are
    read one view ahead in a thread, so disk and decoding overlap the training step."""

    def __init__(self, split: Split, device: torch.device, cache: bool) -> None:
        self.device = device
        self.cached = cache
        self.cameras = [camera.to(device) for camera in split.cameras]
        self.times = [float(t) for t in split.times]
        self.images: Sequence[Tensor] = split.images
        self.masks: Sequence[Tensor] | None = split.masks
        if cache:
            self.images = [self._to_float(image) for image in split.images]
            if split.masks is not None:
                self.masks = [self._to_float(mask) for mask in split.masks]
            for source in (split.images, split.masks):
                if isinstance(source, LazyImages):
                    source.clear()  # the float copies serve from now on
        lazy = isinstance(split.images, LazyImages) or isinstance(split.masks, LazyImages)
        self._pool = ThreadPoolExecutor(1) if lazy and not cache else None
        self._ahead: tuple[int, Future[tuple[Tensor, Tensor | None]]] | None = None

    def _to_float(self, image: Tensor) -> Tensor:
        return image.to(self.device, non_blocking=True).float().div_(255.0)

    def _read(self, index: int) -> tuple[Tensor, Tensor | None]:
        return self.images[index], None if self.masks is None else self.masks[index]

    def read_ahead(self, index: int) -> None:
        """Start reading view `index` (lazy splits only); its `batch` then waits for it."""
        if self._pool is not None and 0 <= index < len(self):
            if self._ahead is None or self._ahead[0] != index:
                self._ahead = (index, self._pool.submit(self._read, index))

    def batch(self, index: int) -> TrainBatch:
        if self._ahead is not None and self._ahead[0] == index:
            image, mask = self._ahead[1].result()
        else:
            image, mask = self._read(index)
        self._ahead = None
        if not self.cached:
            image = self._to_float(image)
            mask = None if mask is None else self._to_float(mask)
        return TrainBatch(self.cameras[index], self.times[index], image, mask, index)

    def __len__(self) -> int:
        return len(self.cameras)


def _float_bytes(split: Split) -> int:
    """Bytes of the split as float32 (sizes read without loading lazy images)."""
    pixels = 0
    for index in range(len(split.images)):
        height, width = image_size(split.images, index)
        pixels += height * width
    channels = 3 + (1 if split.masks is not None else 0)
    return 4 * channels * pixels


class DataManager:
    """Serves shuffled training views and ordered evaluation views.

    The training order is a fresh permutation each epoch. Permutation e is drawn from
    a generator seeded with (s + e), where s is drawn once from the generator given to
    the constructor: runs are reproducible from that generator, and the whole sequence
    state is three integers (see `state_dict`), independent of whoever else uses it.
    """

    def __init__(
        self,
        scene: SceneData,
        config: DataConfig,
        device: torch.device,
        generator: torch.Generator,
    ) -> None:
        if len(scene.train) == 0:
            raise DatasetError(f"{scene.name}: the train split is empty")
        self.scene = scene
        self.config = config
        self.device = torch.device(device)
        self.background = scene.background.to(self.device)
        budget = config.device_cache_bytes
        served: dict[int, _ServedSplit] = {}  # by id: val may be the test split itself
        self._splits: dict[str, _ServedSplit] = {}
        for name in ("train", "val", "test"):
            split: Split = getattr(scene, name)
            if id(split) not in served:
                cost = _float_bytes(split)
                cache = cost <= budget
                budget -= cost if cache else 0
                served[id(split)] = _ServedSplit(split, self.device, cache)
            self._splits[name] = served[id(split)]
        self._earliest = min(self._splits["train"].times, default=0.0)
        self._seed = int(torch.randint(0, 2**62, (1,), generator=generator))
        self._epoch = 0
        self._position = 0
        self._order = self._permutation(0)
        train_times = self._splits["train"].times
        self._by_time = sorted(range(len(train_times)), key=train_times.__getitem__)
        self._sorted_times = [train_times[i] for i in self._by_time]
        self._frontier_draws = 0

    @cached_property
    def fixed_cameras(self) -> FixedCameras | None:
        """The training views' fixed cameras and their temporal medians (None without any):
        they depend on the images only, so they are read once, when first asked for."""
        return FixedCameras.of(self.scene.train)

    @property
    def num_train(self) -> int:
        return len(self._splits["train"])

    @property
    def epoch(self) -> int:
        """Completed passes over the train split."""
        return self._epoch

    def _permutation(self, epoch: int) -> list[int]:
        generator = torch.Generator().manual_seed(self._seed + epoch)
        return torch.randperm(self.num_train, generator=generator).tolist()

    def next_train(self, max_time: float = 1.0) -> TrainBatch:
        """The next training view; every view comes once per epoch, in shuffled order.

        Views later than `max_time` are passed over in this epoch (a time curriculum); if
        none is that early, the earliest views stand in.
        """
        served = self._splits["train"]
        max_time = max(max_time, self._earliest)
        while True:
            if self._position >= len(self._order):
                self._epoch += 1
                self._position = 0
                self._order = self._permutation(self._epoch)
            index = self._order[self._position]
            self._position += 1
            if served.times[index] <= max_time:
                break
        batch = served.batch(index)
        if self._position < len(self._order):
            served.read_ahead(self._order[self._position])
        return batch

    def _window_end(self, max_time: float) -> int:
        """How many training views, in time order, have t ≤ max_time; when none has, the
        earliest views stand in (as in `next_train`)."""
        return bisect_right(self._sorted_times, max(max_time, self._earliest))

    def next_frontier(self, max_time: float, span: float) -> TrainBatch:
        """A training view from the newest `span` of the time window: drawn at random from
        those with max_time − span ≤ t ≤ max_time (the latest views before max_time when
        none is that recent). Draw k uses a generator seeded with (s + 2⁶² + k), so the
        draws never repeat the epochs' permutations and resume exactly from a counter.
        """
        served = self._splits["train"]
        times = self._sorted_times
        end = self._window_end(max_time)
        low = min(max_time - span, times[end - 1])
        start = bisect_left(times, low, hi=end)
        generator = torch.Generator().manual_seed(self._seed + 2**62 + self._frontier_draws)
        self._frontier_draws += 1
        pick = start + int(torch.randint(end - start, (1,), generator=generator))
        return served.batch(self._by_time[pick])

    def train_poses(self, max_time: float = 1.0, limit: int = 0) -> list[tuple[Camera, float]]:
        """Camera and time of each training view with t ≤ max_time (the earliest views when
        none is that early), in time order, without reading an image. With `limit` > 0, at
        most that many, spread evenly over the list."""
        if limit < 0:
            raise ValueError(f"limit must be ≥ 0, got {limit}")
        served = self._splits["train"]
        end = self._window_end(max_time)
        picks = (
            range(end) if limit == 0 or end <= limit else [i * end // limit for i in range(limit)]
        )
        return [(served.cameras[self._by_time[i]], self._sorted_times[i]) for i in picks]

    def views(self, split: str) -> Iterator[TrainBatch]:
        """Every view of "train", "val" or "test", in order."""
        if split not in self._splits:
            raise ValueError(f"unknown split {split!r}: use train, val or test")
        served = self._splits[split]
        for index in range(len(served)):
            batch = served.batch(index)
            served.read_ahead(index + 1)
            yield batch

    def num_views(self, split: str) -> int:
        if split not in self._splits:
            raise ValueError(f"unknown split {split!r}: use train, val or test")
        return len(self._splits[split])

    def state_dict(self) -> dict[str, int]:
        """Where the training sequence stands; `load_state_dict` continues it exactly."""
        return {
            "seed": self._seed,
            "epoch": self._epoch,
            "position": self._position,
            "num_train": self.num_train,
            "frontier_draws": self._frontier_draws,
        }

    def load_state_dict(self, state: dict[str, int]) -> None:
        if int(state["num_train"]) != self.num_train:
            raise ValueError(
                f"state is for {state['num_train']} train views, this scene has {self.num_train}"
            )
        position = int(state["position"])
        if not 0 <= position <= self.num_train or int(state["epoch"]) < 0:
            raise ValueError(f"invalid datamanager state {state}")
        self._seed = int(state["seed"])
        self._epoch = int(state["epoch"])
        self._position = position
        self._order = self._permutation(self._epoch)
        self._frontier_draws = int(state.get("frontier_draws", 0))  # absent before it existed

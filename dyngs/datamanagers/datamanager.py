"""Find and parse a dataset, then serve training batches and evaluation views.

Letters: H×W image.
"""

from __future__ import annotations

import dataclasses
from bisect import bisect_right
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
from dyngs.datamanagers.sampler import STRATUM_SEED_STRIDE, ViewSampler, strata
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
    full: TrainBatch | None = None
    """The whole view, when this one is it shrunk (`coarse`); None when it is whole."""

    def coarse(self, factor: int) -> TrainBatch:
        """This view at 1/`factor` of its resolution: the image and mask area-averaged (as
        `--downscale` shrinks images on loading) to `Camera.scaled`'s size, and the camera
        scaled alike. `full` keeps the whole view (`Objective.pixel_weights` reads it)."""
        if factor == 1:
            return self
        camera = self.camera.scaled(1.0 / factor)
        return TrainBatch(camera, self.time, area_resize(self.image, camera),
                          None if self.mask is None else area_resize(self.mask, camera),
                          self.index, self)  # fmt: skip


def area_resize(image: Float[Tensor, "H W C"], camera: Camera) -> Float[Tensor, "h w C"]:
    """`image` area-averaged to the camera's size: each output pixel the mean of the input
    pixels under it (adaptive average pooling; where the factor divides a side, exactly
    the block means `--downscale` makes)."""
    chw = image.permute(2, 0, 1)[None]
    size = (camera.height, camera.width)
    shrunk = torch.nn.functional.interpolate(chw, size=size, mode="area")
    return shrunk[0].permute(1, 2, 0).contiguous()


class _ServedSplit:
    """A split's cameras on the device and its images either as float32 on the device
    (converted once) or as uint8 on the CPU (converted per batch). Lazy uint8 images are
    read one view ahead in a thread, so disk and decoding overlap the training step.
    With `held`, only those views' images are served (another process serves the rest)."""

    def __init__(
        self, split: Split, device: torch.device, cache: bool, held: set[int] | None = None
    ) -> None:
        self.device = device
        self.cached = cache
        self.held = held
        self.cameras = [camera.to(device) for camera in split.cameras]
        self.times = [float(t) for t in split.times]
        self.images: Sequence[Tensor | None] = split.images
        self.masks: Sequence[Tensor | None] | None = split.masks
        if cache:
            self.images = self._converted(split.images)
            if split.masks is not None:
                self.masks = self._converted(split.masks)
            for source in (split.images, split.masks):
                if isinstance(source, LazyImages):
                    source.clear()  # the float copies serve from now on
        lazy = isinstance(split.images, LazyImages) or isinstance(split.masks, LazyImages)
        self._pool = ThreadPoolExecutor(1) if lazy and not cache else None
        self._ahead: tuple[int, Future[tuple[Tensor, Tensor | None]]] | None = None

    def __contains__(self, index: int) -> bool:
        """Whether view `index` is served here."""
        return self.held is None or index in self.held

    def _converted(self, images: Sequence[Tensor]) -> list[Tensor | None]:
        """Float copies on the device of the served views (None for the others)."""
        return [self._to_float(images[i]) if i in self else None for i in range(len(images))]

    def _to_float(self, image: Tensor) -> Tensor:
        return image.to(self.device, non_blocking=True).float().div_(255.0)

    def _read(self, index: int) -> tuple[Tensor, Tensor | None]:
        if index not in self:
            raise ValueError(f"view {index} is served by another process")
        image = self.images[index]
        mask = None if self.masks is None else self.masks[index]
        assert image is not None
        return image, mask

    def read_ahead(self, index: int) -> None:
        """Start reading view `index` (lazy splits only); its `batch` then waits for it."""
        if self._pool is not None and 0 <= index < len(self) and index in self:
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


class HeldFrames(Sequence[Tensor]):
    """A split's frames of which this process holds only some; asking for another is a
    bug (the process renders only its own views), and says so."""

    def __init__(self, frames: dict[int, Tensor], length: int) -> None:
        self._frames = frames
        self._length = length

    def __len__(self) -> int:
        return self._length

    def __getitem__(self, index: int) -> Tensor:  # type: ignore[override]
        if index not in self._frames:
            raise ValueError(f"frame {index} is held by another process")
        return self._frames[index]


def _float_bytes(split: Split, held: set[int] | None = None) -> int:
    """Bytes of the split (of its `held` views) as float32, sizes read without loading
    lazy images."""
    pixels = 0
    for index in range(len(split.images)):
        if held is not None and index not in held:
            continue
        height, width = image_size(split.images, index)
        pixels += height * width
    channels = 3 + (1 if split.masks is not None else 0)
    return 4 * channels * pixels


class DataManager:
    """Serves shuffled training views and ordered evaluation views.

    A step draws `batch_views` views, one from each stratum of the training views
    (`dyngs.datamanagers.sampler`); each stratum's order is a fresh permutation every
    epoch. The strata's seeds come from one number s drawn from the generator given to
    the constructor: runs are reproducible from that generator, and the whole sequence
    state is a few integers per stratum (see `state_dict`), independent of whoever else
    uses it. With one view per step, the one stratum's seed is s itself.

    `shard` (rank, processes) keeps only the images of the strata that rank renders
    (strata rank, rank + processes, …): every rank draws the same views, and each holds
    and converts only its share, so memory per process falls with the process count.
    """

    def __init__(
        self,
        scene: SceneData,
        config: DataConfig,
        device: torch.device,
        generator: torch.Generator,
        batch_views: int = 1,
        shard: tuple[int, int] = (0, 1),
    ) -> None:
        if len(scene.train) == 0:
            raise DatasetError(f"{scene.name}: the train split is empty")
        if batch_views > len(scene.train):
            raise ConfigError(
                f"--batch-views {batch_views} is more than the {len(scene.train)} training "
                f"views of {scene.name}"
            )
        self.scene = scene
        self.config = config
        self.device = torch.device(device)
        self.background = scene.background.to(self.device)
        train_times = [float(t) for t in scene.train.times]
        self.strata = strata(train_times, batch_views)
        rank, processes = shard
        self.held = sorted(i for stratum in self.strata[rank::processes] for i in stratum)
        # Evaluation runs on rank 0: other ranks keep no float copies of val and test.
        budget = config.device_cache_bytes
        self._splits = self._serve(scene, budget, set(self.held), evaluates=rank == 0)
        self._earliest = min(train_times)
        seed = int(torch.randint(0, 2**62, (1,), generator=generator))
        self.samplers = [
            ViewSampler(train_times, views, seed + k * STRATUM_SEED_STRIDE)
            for k, views in enumerate(self.strata)
        ]
        self._stratum_of = {i: k for k, views in enumerate(self.strata) for i in views}
        self._by_time = sorted(range(len(train_times)), key=train_times.__getitem__)
        self._sorted_times = [train_times[i] for i in self._by_time]
        distinct = torch.tensor(sorted(set(train_times)), dtype=torch.float64)
        self.time_spacing = float(distinct.diff().median()) if len(distinct) > 1 else 0.0
        """Median spacing of the distinct training times (0 for a single time)."""

    def _serve(
        self, scene: SceneData, budget: int, held: set[int], evaluates: bool = True
    ) -> dict[str, _ServedSplit]:
        """Each split served, float images on the device while `budget` bytes last (of
        the train split, only the `held` views; of the others, only where `evaluates`)."""
        served: dict[int, _ServedSplit] = {}  # by id: val may be the test split itself
        splits: dict[str, _ServedSplit] = {}
        for name in ("train", "val", "test"):
            split: Split = getattr(scene, name)
            if id(split) not in served:
                whole = split is not scene.train or len(held) == len(split)
                keep = None if whole else held
                cost = _float_bytes(split, keep)
                cache = cost <= budget and (evaluates or split is scene.train)
                budget -= cost if cache else 0
                served[id(split)] = _ServedSplit(split, self.device, cache, keep)
            splits[name] = served[id(split)]
        return splits

    @cached_property
    def fixed_cameras(self) -> FixedCameras | None:
        """The training views' fixed cameras and their temporal medians (None without any):
        they depend on the images only, so they are read once, when first asked for."""
        return FixedCameras.of(self.scene.train)

    @property
    def num_train(self) -> int:
        return len(self._splits["train"])

    def release_others(self) -> None:
        """Drop this process's references to the training images other processes serve
        (call once whatever reads every image, such as the fixed cameras' medians, has)."""
        train = self.scene.train
        if len(self.held) == len(train) or isinstance(train.images, LazyImages):
            return  # lazy frames are read on demand: only the held ones ever are
        held = set(self.held)
        images = HeldFrames({i: train.images[i] for i in held}, len(train))
        masks = None
        if train.masks is not None:
            masks = HeldFrames({i: train.masks[i] for i in held}, len(train))
        self.scene = dataclasses.replace(self.scene, train=dataclasses.replace(
            train, images=images, masks=masks))  # fmt: skip

    @property
    def batch_views(self) -> int:
        return len(self.samplers)

    @property
    def epoch(self) -> int:
        """Completed passes over the first stratum (every view, with one view per step)."""
        return self.samplers[0].epoch

    def next_train(self, max_time: float = 1.0) -> TrainBatch:
        """The next training view of the first stratum (with one view per step: of all
        views, each once per epoch in shuffled order). Views later than `max_time` are
        passed over in this epoch (a time curriculum); if none is that early, the
        earliest views stand in."""
        return self.train_batch(self.samplers[0].next(max_time))

    def next_frontier(self, max_time: float, span: float) -> TrainBatch:
        """A training view of the first stratum from the newest `span` of the time window
        (`ViewSampler.frontier`)."""
        return self.train_batch(self.samplers[0].frontier(max_time, span))

    def next_views(self, max_time: float, frontier_span: float | None = None) -> list[int]:
        """A step's views, one per stratum (the same on every rank): the next of each
        stratum's epoch within `max_time`, or, with `frontier_span`, drawn from the newest
        part of the window."""
        if frontier_span is None:
            return [sampler.next(max_time) for sampler in self.samplers]
        return [sampler.frontier(max_time, frontier_span) for sampler in self.samplers]

    def train_batch(self, index: int) -> TrainBatch:
        """Training view `index` (one this process holds). The next view of its stratum's
        epoch is read ahead (lazy splits), to overlap the step."""
        served = self._splits["train"]
        batch = served.batch(index)
        upcoming = self.samplers[self._stratum_of[index]].upcoming()
        if upcoming is not None and upcoming in served:
            served.read_ahead(upcoming)
        return batch

    def _window_end(self, max_time: float) -> int:
        """How many training views, in time order, have t ≤ max_time; when none has, the
        earliest views stand in (as in `next_train`)."""
        return bisect_right(self._sorted_times, max(max_time, self._earliest))

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

    def state_dict(self) -> dict[str, object]:
        """Where the training sequence stands; `load_state_dict` continues it exactly. The
        first stratum's state at the top level (all of it, with one view per step)."""
        state: dict[str, object] = {**self.samplers[0].state_dict(), "num_train": self.num_train}
        if self.batch_views > 1:
            state["strata"] = [sampler.state_dict() for sampler in self.samplers]
        return state

    def load_state_dict(self, state: dict[str, object]) -> None:
        if int(state["num_train"]) != self.num_train:  # type: ignore[call-overload]
            raise ValueError(
                f"state is for {state['num_train']} train views, this scene has {self.num_train}"
            )
        saved = state.get("strata", [state])
        assert isinstance(saved, list)
        if len(saved) != self.batch_views:
            raise ConfigError(
                f"the checkpoint was trained with --batch-views {len(saved)}, this run has "
                f"{self.batch_views}"
            )
        for sampler, sampler_state in zip(self.samplers, saved, strict=True):
            sampler.load_state_dict(sampler_state)

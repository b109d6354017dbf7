"""Find and parse a dataset, then serve training batches and evaluation views.

Letters: H×W image.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import torch
from jaxtyping import Float
from torch import Tensor

from dyngs.datamanagers.base import DatasetError, SceneData, Split
from dyngs.datamanagers.dnerf import parse_dnerf
from dyngs.datamanagers.procedural import demo_path
from dyngs.errors import ConfigError
from dyngs.types import Camera

DEMO = "demo"
"""The `--data` value that selects the built-in procedural scene."""


@dataclass(frozen=True)
class DataConfig:
    """How a dataset is loaded and served."""

    downscale: int = 1
    """Divide image width and height by this factor."""
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """RGB the RGBA images are composited over (and renders use)."""
    num_random_points: int = 20_000
    """Initial points drawn in the scene box when the folder has no point cloud."""
    device_cache_bytes: int = 2 << 30
    """Keep float images on the training device when they fit in this many bytes."""

    def __post_init__(self) -> None:
        if self.downscale < 1:
            raise ConfigError(f"--downscale must be ≥ 1, got {self.downscale}")
        if len(self.background) != 3 or not all(0.0 <= c <= 1.0 for c in self.background):
            raise ConfigError(f"--background must be three values in [0, 1], got {self.background}")
        if self.num_random_points < 1:
            raise ConfigError(f"--num-random-points must be ≥ 1, got {self.num_random_points}")
        if self.device_cache_bytes < 0:
            raise ConfigError(f"--device-cache-bytes must be ≥ 0, got {self.device_cache_bytes}")


@dataclass(frozen=True)
class DatasetFormat:
    name: str
    marker: str
    """A file at the top of the folder that identifies the format."""
    parse: Callable[[Path, DataConfig, int], SceneData]


def _parse_dnerf(path: Path, config: DataConfig, seed: int) -> SceneData:
    return parse_dnerf(path, config.downscale, config.background, config.num_random_points, seed)


FORMATS: tuple[DatasetFormat, ...] = (
    DatasetFormat("dnerf", "transforms_train.json", _parse_dnerf),
)
"""On-disk formats, tried in order: the first whose marker file exists parses the folder."""


def load_scene(data: str | Path, config: DataConfig, seed: int = 0) -> SceneData:
    """Parse `data`: "demo" (the built-in procedural scene) or a dataset folder.

    `seed` seeds the random initial points of folders that have no point cloud.
    """
    if str(data) == DEMO:
        return _parse_dnerf(demo_path(), config, seed)
    path = Path(data).expanduser()
    if not path.exists():
        raise DatasetError(f"{path}: does not exist")
    for fmt in FORMATS:
        if (path / fmt.marker).is_file():
            return fmt.parse(path, config, seed)
    expected = " or ".join(fmt.marker for fmt in FORMATS)
    raise DatasetError(f"{path}: not a dataset folder (expected {expected} in it, or '{DEMO}')")


@dataclass
class TrainBatch:
    """One view: its camera and time, the image (float32 in [0, 1], on the device)."""

    camera: Camera
    time: float
    image: Float[Tensor, "H W 3"]
    mask: Float[Tensor, "H W 1"] | None
    """Alpha of the source image in [0, 1], when it had one."""
    index: int
    """Position of the view in its split."""


class _ServedSplit:
    """A split's cameras on the device and its images either as float32 on the device
    (converted once) or as uint8 on the CPU (converted per batch)."""

    def __init__(self, split: Split, device: torch.device, cache: bool) -> None:
        self.device = device
        self.cached = cache
        self.cameras = [camera.to(device) for camera in split.cameras]
        self.times = [float(t) for t in split.times]
        self.images = [self._prepare(image, cache) for image in split.images]
        self.masks = None if split.masks is None else [self._prepare(m, cache) for m in split.masks]

    def _prepare(self, image: Tensor, cache: bool) -> Tensor:
        return self._to_float(image) if cache else image

    def _to_float(self, image: Tensor) -> Tensor:
        return image.to(self.device, non_blocking=True).float().div_(255.0)

    def batch(self, index: int) -> TrainBatch:
        image = self.images[index]
        mask = None if self.masks is None else self.masks[index]
        if not self.cached:
            image = self._to_float(image)
            mask = None if mask is None else self._to_float(mask)
        return TrainBatch(self.cameras[index], self.times[index], image, mask, index)

    def __len__(self) -> int:
        return len(self.cameras)


def _float_bytes(split: Split) -> int:
    pixels = sum(image.shape[0] * image.shape[1] for image in split.images)
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
        self._seed = int(torch.randint(0, 2**62, (1,), generator=generator))
        self._epoch = 0
        self._position = 0
        self._order = self._permutation(0)

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

    def next_train(self) -> TrainBatch:
        """The next training view; every view comes once per epoch, in shuffled order."""
        if self._position >= len(self._order):
            self._epoch += 1
            self._position = 0
            self._order = self._permutation(self._epoch)
        index = self._order[self._position]
        self._position += 1
        return self._splits["train"].batch(index)

    def views(self, split: str) -> Iterator[TrainBatch]:
        """Every view of "train", "val" or "test", in order."""
        if split not in self._splits:
            raise ValueError(f"unknown split {split!r}: use train, val or test")
        served = self._splits[split]
        for index in range(len(served)):
            yield served.batch(index)

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

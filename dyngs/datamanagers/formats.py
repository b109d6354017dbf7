"""Dataset formats by name: `--format NAME`, or found from a marker file in the folder.

`FORMATS` holds dyngs's own (D-NeRF, Panoptic, DyNeRF, Nerfies); an installed package
adds its own through the `dyngs.formats` entry-point group, naming a `DatasetFormat`:

    [project.entry-points."dyngs.formats"]
    my-format = "my_package.data:MY_FORMAT"

With `--format auto` the formats are tried in registration order, built-in ones first:
the first whose marker file is in the folder parses it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from dyngs.datamanagers.base import SceneData
from dyngs.datamanagers.dnerf import parse_dnerf
from dyngs.datamanagers.dynerf import parse_dynerf
from dyngs.datamanagers.nerfies import parse_nerfies
from dyngs.datamanagers.panoptic import parse_panoptic
from dyngs.registry import Registry

if TYPE_CHECKING:
    from dyngs.datamanagers.datamanager import DataConfig


@dataclass(frozen=True)
class DatasetFormat:
    """An on-disk format: how to recognise a folder of it, and how to parse one."""

    marker: str
    """A file at the top of the folder that identifies the format."""
    parse: Callable[[Path, DataConfig, int], SceneData]
    """parse(folder, data config, seed) → the scene; bad input raises a one-line
    `DatasetError` naming the file. `seed` seeds any random initial points."""
    description: str = ""
    """One line for `--help` and error messages."""


def _check(item: object) -> str | None:
    return None if isinstance(item, DatasetFormat) else "is not a DatasetFormat"


def _dnerf(path: Path, config: DataConfig, seed: int) -> SceneData:
    return parse_dnerf(path, config.downscale, config.background, config.num_random_points, seed)


CaptureParser = Callable[[Path, int, tuple[float, float, float], int, int, int], SceneData]
"""parse(path, downscale, background, num_random_points, seed, cache_bytes)."""


def _capture(parse: CaptureParser) -> Callable[[Path, DataConfig, int], SceneData]:
    """A format read lazily (Panoptic, DyNeRF, Nerfies), which also takes the host cache."""

    def run(path: Path, config: DataConfig, seed: int) -> SceneData:
        return parse(
            path,
            config.downscale,
            config.background,
            config.num_random_points,
            seed,
            config.host_cache_bytes,
        )

    return run


def _panoptic(path: Path, config: DataConfig, seed: int) -> SceneData:
    return parse_panoptic(
        path,
        config.downscale,
        config.background,
        config.num_random_points,
        seed,
        config.host_cache_bytes,
        config.holdout,
    )


FORMATS: Registry[DatasetFormat] = Registry("dataset format", "dyngs.formats", _check)
FORMATS.register(
    "dnerf", DatasetFormat("transforms_train.json", _dnerf, "D-NeRF / Blender synthetic scenes")
)
FORMATS.register(
    "panoptic",
    DatasetFormat("train_meta.json", _panoptic, "Dynamic 3D Gaussians (Panoptic)"),
)
FORMATS.register(
    "dynerf",
    DatasetFormat("poses_bounds.npy", _capture(parse_dynerf), "DyNeRF / Neural 3D Video"),
)
FORMATS.register(
    "nerfies", DatasetFormat("dataset.json", _capture(parse_nerfies), "Nerfies / HyperNeRF")
)

"""What a dataset parser yields, whatever the on-disk format.

Letters: F frames in a split, H×W image, P initial points.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from jaxtyping import Float, UInt8
from torch import Tensor

from dyngs.errors import UserError
from dyngs.types import Camera, SceneBox


class DatasetError(UserError, ValueError):
    """Bad input data. The message is one line naming the file and the problem."""


@dataclass
class Split:
    """The frames of one split: a camera, a time in [0, 1] and an image each.

    Images are kept as uint8 on the CPU (a quarter of float32's memory); the datamanager
    converts them once, on the training device, when they fit.
    """

    cameras: list[Camera]
    times: Float[Tensor, " F"]
    images: list[UInt8[Tensor, "H W 3"]]
    masks: list[UInt8[Tensor, "H W 1"]] | None = None
    paths: list[Path] | None = None

    def __len__(self) -> int:
        return len(self.cameras)


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

    @property
    def num_timestamps(self) -> int:
        return int(torch.unique(self.train.times).numel())

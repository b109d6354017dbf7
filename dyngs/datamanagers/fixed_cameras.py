"""Fixed cameras: views that share one camera at different times, and what each of that
camera's pixels shows most of the time.

A camera that stays put while time passes sees motion directly: a pixel that differs
from its temporal median shows something that is not usually there. The static/dynamic
split (dyngs/engine/motion.py) and the change-weighted photometric loss
(`Trainer.loss_weights`, `--losses.change-weight`) both read it from here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from jaxtyping import Bool, Float, UInt8
from torch import Tensor

from dyngs.datamanagers.base import Split
from dyngs.types import Camera

PIXEL_CHANGE = 0.1
"""How far (largest channel difference, in [0, 1]) a pixel must be from its camera's
temporal median to show something that is not usually there: about 25/255, above sensor
and compression noise, below the contrast of an object against what is behind it."""

MEDIAN_FRAMES = 64
"""Frames per fixed camera that the temporal median is taken over (evenly spread)."""


def dilate(values: Float[Tensor, "H W"]) -> Float[Tensor, "H W"]:
    """Each pixel's largest value over itself and its eight neighbours: a point on a
    moving edge may sit just beside the change."""
    return torch.nn.functional.max_pool2d(values[None, None], 3, 1, 1)[0, 0]


def fixed_camera_groups(split: Split, min_times: int = 3) -> list[list[int]]:
    """Views taken by the same camera at different times (≥ `min_times` of them)."""
    groups: dict[tuple[float, ...], list[int]] = {}
    for i, camera in enumerate(split.cameras):
        key = (
            *(round(float(v), 5) for v in camera.world_to_camera[:3].reshape(-1)),
            round(camera.fx, 3),
            round(camera.fy, 3),
            round(camera.cx, 3),
            round(camera.cy, 3),
            camera.width,
            camera.height,
        )
        groups.setdefault(key, []).append(i)
    return [
        views
        for views in groups.values()
        if len({float(split.times[i]) for i in views}) >= min_times
    ]


@dataclass
class FixedCameras:
    """A split's fixed cameras: for each, its views in time order, its camera, and its
    temporal median image. It depends on the images only, so a run reads it once."""

    views: list[list[int]]
    cameras: list[Camera]
    medians: list[UInt8[Tensor, "H W 3"]]
    """Per camera and pixel, the median over up to `MEDIAN_FRAMES` of its frames, evenly
    spread in time."""
    _camera_of: dict[int, int] = field(init=False, repr=False)
    _on_device: dict[torch.device, list[Tensor]] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self._camera_of = {i: c for c, views in enumerate(self.views) for i in views}

    @classmethod
    def of(cls, split: Split) -> FixedCameras | None:
        """None when the split has no fixed cameras (monocular or moving-camera captures)."""
        groups = fixed_camera_groups(split)
        if not groups:
            return None
        views = [sorted(group, key=lambda i: float(split.times[i])) for group in groups]
        medians = []
        for order in views:
            picks = torch.linspace(0, len(order) - 1, min(len(order), MEDIAN_FRAMES)).round()
            stack = torch.stack([split.images[order[int(k)]] for k in picks])
            medians.append(stack.median(dim=0).values)
        return cls(views, [split.cameras[order[0]] for order in views], medians)

    def camera_of(self, index: int) -> int | None:
        """Which fixed camera took view `index` of the split (None: a camera that moves)."""
        return self._camera_of.get(index)

    def distance(self, camera: int, image: Float[Tensor, "H W 3"]) -> Float[Tensor, "H W"]:
        """How far each pixel of `image` (float in [0, 1], as fixed camera `camera` sees
        it) is from that camera's median: the largest difference over the channels."""
        if image.device not in self._on_device:
            self._on_device[image.device] = [m.to(image.device) for m in self.medians]
        median = self._on_device[image.device][camera].to(image.dtype) / 255.0
        return (image - median).abs().amax(-1)

    def changed(
        self, index: int, image: Float[Tensor, "H W 3"], threshold: float
    ) -> Bool[Tensor, "H W"] | None:
        """Pixels of view `index` (`image`) whose `distance`, dilated by one pixel, exceeds
        `threshold`. None when a moving camera took the view."""
        camera = self.camera_of(index)
        if camera is None:
            return None
        return dilate(self.distance(camera, image)) > threshold

"""What a run folder keeps of its scene: every view's camera and time, the scene box and
the background, without a pixel. `dyngs-train` writes it as `scene.json`, so a finished
run renders and exports without its dataset (evaluating still needs the images).

Letters: F views in a split.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import torch
from jaxtyping import Float
from torch import Tensor

from dyngs.errors import DatasetError
from dyngs.io import write_json
from dyngs.types import Camera, SceneBox

SCENE_FILE = "scene.json"
_SPLITS = ("train", "val", "test")


class HasViews(Protocol):
    @property
    def cameras(self) -> list[Camera]: ...

    @property
    def times(self) -> Float[Tensor, " F"]: ...


class HasScene(Protocol):
    """A parsed scene (`SceneData`) or a `SceneInfo`: what a `SceneInfo` is made from."""

    @property
    def name(self) -> str: ...

    @property
    def scene_box(self) -> SceneBox: ...

    @property
    def background(self) -> Float[Tensor, " 3"]: ...

    @property
    def train(self) -> HasViews: ...

    @property
    def val(self) -> HasViews: ...

    @property
    def test(self) -> HasViews: ...


@dataclass
class Views:
    """The views of one split: a camera and a time each."""

    cameras: list[Camera]
    times: Float[Tensor, " F"]

    def __len__(self) -> int:
        return len(self.cameras)


@dataclass
class SceneInfo:
    """A scene without its images (see the module docstring)."""

    name: str
    scene_box: SceneBox
    background: Float[Tensor, " 3"]
    train: Views
    val: Views
    test: Views

    @classmethod
    def of(cls, scene: HasScene) -> SceneInfo:
        splits = {
            name: Views(list(getattr(scene, name).cameras), getattr(scene, name).times.clone())
            for name in _SPLITS
        }
        return cls(scene.name, scene.scene_box, scene.background.clone(), **splits)

    def to_json(self) -> dict[str, Any]:
        """Cameras are listed once each (a fixed rig has few) and views refer to them."""
        cameras: list[dict[str, Any]] = []
        index: dict[str, int] = {}
        views: dict[str, list[list[float]]] = {}
        for name in _SPLITS:
            split: Views = getattr(self, name)
            rows = []
            for camera, t in zip(split.cameras, split.times.tolist(), strict=True):
                entry = _camera_json(camera)
                key = json.dumps(entry, sort_keys=True)
                if key not in index:
                    index[key] = len(cameras)
                    cameras.append(entry)
                rows.append([index[key], t])
            views[name] = rows
        return {
            "name": self.name,
            "box": [list(self.scene_box.lower), list(self.scene_box.upper)],
            "background": self.background.tolist(),
            "cameras": cameras,
            "views": views,
        }

    @classmethod
    def from_json(cls, data: Any, where: str) -> SceneInfo:
        """Parse `to_json`'s output; a DatasetError naming `where` if it is malformed."""
        try:
            cameras = [_camera(entry) for entry in data["cameras"]]
            splits = {}
            for name in _SPLITS:
                rows = data["views"][name]
                splits[name] = Views(
                    [cameras[int(i)] for i, _ in rows],
                    torch.tensor([float(t) for _, t in rows], dtype=torch.float32),
                )
            lower, upper = data["box"]
            return cls(
                name=str(data["name"]),
                scene_box=SceneBox(tuple(lower), tuple(upper)),
                background=torch.tensor(data["background"], dtype=torch.float32),
                **splits,
            )
        except (KeyError, IndexError, TypeError, ValueError) as error:
            raise DatasetError(
                f"{where}: not a dyngs scene description ({type(error).__name__}: {error})"
            ) from None

    def write(self, path: Path) -> None:
        write_json(path, self.to_json())

    @classmethod
    def read(cls, path: Path) -> SceneInfo:
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as error:
            raise DatasetError(
                f"{path}: malformed JSON at line {error.lineno}, column {error.colno}"
            ) from None
        return cls.from_json(data, str(path))


def _camera_json(camera: Camera) -> dict[str, Any]:
    return {
        "fx": camera.fx,
        "fy": camera.fy,
        "cx": camera.cx,
        "cy": camera.cy,
        "width": camera.width,
        "height": camera.height,
        "near": camera.near,
        "far": camera.far,
        "world_to_camera": camera.world_to_camera.tolist(),
        "dtype": str(camera.world_to_camera.dtype).removeprefix("torch."),
    }


def _camera(entry: dict[str, Any]) -> Camera:
    dtype = getattr(torch, str(entry.get("dtype", "float32")))
    if not isinstance(dtype, torch.dtype):
        raise ValueError(f"unknown dtype {entry.get('dtype')!r}")
    return Camera(
        fx=float(entry["fx"]),
        fy=float(entry["fy"]),
        cx=float(entry["cx"]),
        cy=float(entry["cy"]),
        world_to_camera=torch.tensor(entry["world_to_camera"], dtype=dtype),
        width=int(entry["width"]),
        height=int(entry["height"]),
        near=float(entry["near"]),
        far=float(entry["far"]),
    )

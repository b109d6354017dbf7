"""Tiny D-NeRF folders written from known cameras, and the path to the shared real data.

The Blender camera-to-world matrices are built here straight from the convention (a
camera looks down its −z axis with y up), not with the parser's conversion helpers, so
the tests check the parser against the convention rather than against itself.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

SHARED_DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"


def shared_scene(name: str) -> Path:
    """../shared/data/NAME, or skip the test when it is not there."""
    path = SHARED_DATA / name
    if not (path / "transforms_train.json").is_file():
        pytest.skip(f"real scene {name} not found at {path.resolve()} (shared data absent)")
    return path


def random_c2w(rng: np.random.Generator, radius: float = 4.0) -> np.ndarray:
    """A Blender camera-to-world matrix: a random proper rotation, looking roughly at the
    origin from `radius` away."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    c2w = np.eye(4)
    c2w[:3, :3] = q
    # The camera looks along its −z column; put the origin in front of it.
    c2w[:3, 3] = q[:, 2] * radius + rng.normal(scale=0.2, size=3)
    return c2w


@dataclass
class FrameSpec:
    c2w: np.ndarray
    time: float
    image: np.ndarray
    """uint8 RGB or RGBA."""
    extra: dict[str, Any] = field(default_factory=dict)
    """Per-frame keys (fl_x, cx, …)."""


def write_dataset(
    folder: Path,
    splits: dict[str, list[FrameSpec]],
    top: dict[str, Any] | None = None,
) -> Path:
    """Write transforms_{split}.json and PNGs (split/r_000.png, file_path without .png)."""
    folder.mkdir(parents=True, exist_ok=True)
    for split, frames in splits.items():
        (folder / split).mkdir(exist_ok=True)
        entries = []
        for index, frame in enumerate(frames):
            name = f"r_{index:03d}"
            image = frame.image
            bgr = image[..., [2, 1, 0, 3]] if image.shape[2] == 4 else image[..., ::-1]
            assert cv2.imwrite(str(folder / split / f"{name}.png"), np.ascontiguousarray(bgr))
            entries.append(
                {
                    "file_path": f"./{split}/{name}",
                    "time": frame.time,
                    "transform_matrix": frame.c2w.tolist(),
                    **frame.extra,
                }
            )
        meta = {**(top if top is not None else {"camera_angle_x": math.radians(50)})}
        meta["frames"] = entries
        (folder / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))
    return folder


def small_dataset(folder: Path, width: int = 8, height: int = 6, alpha: bool = True) -> Path:
    """A valid 3 / 2 / 2-frame dataset of `width`×`height` images."""
    rng = np.random.default_rng(0)
    channels = 4 if alpha else 3

    def frames(count: int, offset: float) -> list[FrameSpec]:
        return [
            FrameSpec(
                random_c2w(rng),
                min(1.0, offset + i / 4),
                rng.integers(0, 256, size=(height, width, channels), dtype=np.uint8),
            )
            for i in range(count)
        ]

    return write_dataset(
        folder, {"train": frames(3, 0.0), "val": frames(2, 0.1), "test": frames(2, 0.2)}
    )

"""`dyngs-render`: a video of a trained run, e.g. `dyngs-render --load-dir outputs/RUN`.

Three camera paths: `test` follows the cameras of a split (test by default) in time
order, each at its own time; `spiral` circles the scene-box centre at the training
cameras' mean distance and height, rising and falling once, while time runs from 0 to 1;
`fixed` holds one camera of a split while time runs from 0 to 1. The MP4 is written with
OpenCV ('mp4v').
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
import torch
import tyro
from jaxtyping import Float, UInt8
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from dyngs.datamanagers.scene_info import SceneInfo
from dyngs.engine.writer import to_uint8
from dyngs.errors import ConfigError, UserError
from dyngs.renderers.base import ABSENT_BELOW
from dyngs.runs import LoadedRun, RunOverrides, load_run
from dyngs.tools.common import run_tool
from dyngs.types import Camera

Trajectory = Literal["test", "spiral", "fixed"]

SNAP_DEGREES = 25.0
"""An estimated up direction this close to a world axis is taken to be that axis."""
MAX_ELEVATION = math.radians(80.0)
"""Spiral elevations are kept below this, away from the pole where look-at degenerates."""


def look_at(
    eye: Float[np.ndarray, " 3"], target: Float[np.ndarray, " 3"], up: Float[np.ndarray, " 3"]
) -> Float[np.ndarray, "4 4"]:
    """OpenCV world-to-camera (x right, y down, z forward) at `eye` looking at `target`,
    with `up` (world space) pointing up in the image."""
    forward = target - eye
    forward = forward / np.linalg.norm(forward)
    right = np.cross(-up, forward)
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    w2c = np.eye(4)
    w2c[:3, :3] = rotation
    w2c[:3, 3] = -rotation @ eye
    return w2c


def world_up(mean_up: Float[np.ndarray, " 3"]) -> Float[np.ndarray, " 3"]:
    """The scene's up direction from the mean of the cameras' image-up vectors: snapped
    to the nearest world axis when within SNAP_DEGREES of it (captures are usually
    axis-aligned, and an unevenly spread rig tilts the mean a few degrees), else kept."""
    norm = float(np.linalg.norm(mean_up))
    if norm < 1e-6:
        return np.array([0.0, 0.0, 1.0])
    up = mean_up / norm
    axis = int(np.abs(up).argmax())
    snapped = np.zeros(3)
    snapped[axis] = math.copysign(1.0, up[axis])
    return snapped if abs(up[axis]) >= math.cos(math.radians(SNAP_DEGREES)) else up


def spiral_cameras(
    scene: SceneInfo, frames: int, turns: float = 1.0, swing_degrees: float = 15.0
) -> list[Camera]:
    """`frames` cameras circling the scene-box centre `turns` times.

    Up is the training cameras' mean image-up direction (`world_up`); radius and mean
    elevation are theirs too, and the elevation swings ±`swing_degrees` once over the
    path. Intrinsics are those of the first training camera.
    """
    reference = scene.train.cameras[0]
    centres = np.stack([c.center.double().cpu().numpy() for c in scene.train.cameras])
    # Row 1 of a world-to-camera rotation is the camera's y (image down) in world space.
    ups = -np.stack([c.rotation[1].double().cpu().numpy() for c in scene.train.cameras])
    up = world_up(ups.mean(0))
    target = np.asarray(scene.scene_box.center, dtype=np.float64)
    offsets = centres - target
    heights = offsets @ up
    flat = offsets - heights[:, None] * up
    distance = float(np.linalg.norm(offsets, axis=1).mean())
    elevation = math.atan2(float(heights.mean()), float(np.linalg.norm(flat, axis=1).mean()))
    # Start where the first training camera stands, then turn around `up`.
    e1 = flat[0] if np.linalg.norm(flat[0]) > 1e-9 else np.cross(up, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 1e-9:
        e1 = np.cross(up, [0.0, 1.0, 0.0])
    e1 = e1 / np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    swing = math.radians(swing_degrees)
    cameras = []
    for i in range(frames):
        phase = i / frames
        azimuth = 2 * math.pi * turns * phase
        tilt = elevation + swing * math.sin(2 * math.pi * phase)
        tilt = max(-MAX_ELEVATION, min(MAX_ELEVATION, tilt))
        direction = math.cos(tilt) * (math.cos(azimuth) * e1 + math.sin(azimuth) * e2)
        eye = target + distance * (direction + math.sin(tilt) * up)
        w2c = torch.from_numpy(look_at(eye, target, up)).to(reference.world_to_camera)
        cameras.append(dataclasses.replace(reference, world_to_camera=w2c))
    return cameras


def resize_camera(camera: Camera, scale: float, width: int | None, height: int | None) -> Camera:
    """The camera for another image size: `scale` times its own, or `width`/`height`
    (one alone keeps the aspect ratio). Focal lengths and principal point follow."""
    if width is None and height is None:
        return camera.scaled(scale)
    if width is None:
        width = max(1, round(camera.width * (height or camera.height) / camera.height))
    if height is None:
        height = max(1, round(camera.height * width / camera.width))
    sx, sy = width / camera.width, height / camera.height
    return dataclasses.replace(
        camera,
        fx=camera.fx * sx,
        fy=camera.fy * sy,
        cx=camera.cx * sx,
        cy=camera.cy * sy,
        width=width,
        height=height,
    )


@dataclass(frozen=True)
class RenderConfig:
    """Render a trained run to an MP4 video."""

    load_dir: Path
    """Run folder written by dyngs-train."""
    trajectory: Trajectory = "spiral"
    """Camera path. `test`: the cameras of --split in time order.
    `spiral`: around the scene while time runs 0→1. `fixed`: --camera of --split, time 0→1."""
    output: Path | None = None
    """Video file (default: LOAD_DIR/render_<trajectory>.mp4)."""
    fps: float = 30.0
    """Frames per second of the video."""
    frames: int | None = None
    """Number of frames (default: one per view for `test`, 120 for `spiral`, 60 for `fixed`)."""
    split: Literal["test", "val", "train"] = "test"
    """Split whose cameras `test` and `fixed` use."""
    camera: int = 0
    """Index of the camera in --split for `fixed`."""
    scale: float = 1.0
    """Image size as a multiple of the cameras' own (ignored when --width or --height is set)."""
    width: int | None = None
    """Image width in pixels (alone: height follows the aspect ratio)."""
    height: int | None = None
    """Image height in pixels (alone: width follows the aspect ratio)."""
    turns: float = 1.0
    """Turns around the scene for `spiral`."""
    swing: float = 15.0
    """Elevation swing of `spiral`, ± degrees around the training cameras' mean."""
    run: Annotated[RunOverrides, tyro.conf.OmitArgPrefixes] = field(default_factory=RunOverrides)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise ConfigError(f"--fps must be positive, got {self.fps}")
        if self.frames is not None and self.frames < 1:
            raise ConfigError(f"--frames must be ≥ 1, got {self.frames}")
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise ConfigError(f"--scale must be positive, got {self.scale}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ConfigError(f"--{name} must be ≥ 1, got {value}")


def camera_path(run: LoadedRun, config: RenderConfig) -> list[tuple[Camera, float]]:
    """(camera, time) of every frame, before resizing."""
    scene = run.scene
    if config.trajectory == "spiral":
        count = config.frames or 120
        cameras = spiral_cameras(scene, count, config.turns, config.swing)
        return [(cam, i / max(count - 1, 1)) for i, cam in enumerate(cameras)]
    split = getattr(scene, config.split)
    if len(split) == 0:
        raise ConfigError(f"the {config.split} split of {scene.name} has no views")
    if config.trajectory == "fixed":
        if not 0 <= config.camera < len(split):
            raise ConfigError(
                f"--camera {config.camera}: the {config.split} split has {len(split)} cameras "
                f"(0..{len(split) - 1})"
            )
        count = config.frames or 60
        camera = split.cameras[config.camera]
        return [(camera, i / max(count - 1, 1)) for i in range(count)]
    order = sorted(range(len(split)), key=lambda i: (float(split.times[i]), i))
    count = config.frames or len(order)
    picks = [order[i * len(order) // count] for i in range(count)]  # even resampling
    return [(split.cameras[i], float(split.times[i])) for i in picks]


@torch.no_grad()
def render_frame(run: LoadedRun, camera: Camera, t: float) -> UInt8[np.ndarray, "H W 3"]:
    """One frame of the video: the run's model at time t through `camera`, 8-bit RGB, in
    that camera's colours where it is one of the capture's (`CameraColours`)."""
    background = run.scene.background.to(run.device, torch.float32)
    drawn = run.model.at(t, absent_below=ABSENT_BELOW)
    rgb = run.renderer(drawn, camera.to(run.device), background).rgb
    return to_uint8(run.model.camera_colour(rgb, camera))


@torch.no_grad()
def run_render(config: RenderConfig, console: Console | None = None) -> Path:
    """Render the video; returns its path."""
    console = console or Console()
    run = load_run(config.load_dir, overrides=config.run)
    frames = [
        (resize_camera(cam, config.scale, config.width, config.height).to(run.device), t)
        for cam, t in camera_path(run, config)
    ]
    sizes = {(cam.width, cam.height) for cam, _ in frames}
    if len(sizes) != 1:
        raise ConfigError(
            f"the {config.split} cameras have different image sizes {sorted(sizes)}; "
            "give --width and --height"
        )
    width, height = sizes.pop()
    if width % 2 or height % 2:
        # MPEG-4 encoders store even sizes only (OpenCV would silently crop a pixel).
        even_w, even_h = max(2, width - width % 2), max(2, height - height % 2)
        warnings.warn(
            f"video size {width}×{height} is odd; rendering at {even_w}×{even_h} for MPEG-4",
            stacklevel=2,
        )
        frames = [(resize_camera(cam, 1.0, even_w, even_h), t) for cam, t in frames]
        width, height = even_w, even_h
    output = config.output or run.run_dir / f"render_{config.trajectory}.mp4"
    output.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(
        str(output), cv2.VideoWriter.fourcc(*"mp4v"), config.fps, (width, height)
    )
    if not writer.isOpened():
        raise UserError(f"{output}: OpenCV cannot write an mp4v video here")
    columns = (
        TextColumn(f"[bold]render {config.trajectory}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
    )
    try:
        with Progress(*columns, console=console) as progress:
            task = progress.add_task("render", total=len(frames))
            for camera, t in frames:
                writer.write(cv2.cvtColor(render_frame(run, camera, t), cv2.COLOR_RGB2BGR))
                progress.advance(task)
    finally:
        writer.release()
    console.print(f"wrote {output}: {len(frames)} frames, {width}×{height}, {config.fps:g} fps")
    return output


def main(argv: Sequence[str] | None = None) -> None:
    def body(console: Console) -> None:
        config = tyro.cli(RenderConfig, args=argv, prog="dyngs-render", description=__doc__)
        run_render(config, console)

    run_tool(body)


if __name__ == "__main__":
    main()

"""Frame times of the viewer (dyngs-view) on a trained run, through its own render path.

    python benchmarks/bench_viewer.py --run outputs/RUN

Three figures, each the median over `--rounds` rounds of `--frames` frames:

- `full`: the frame drawn when the view stops, 800 × 800 (a square canvas of that size),
  from the first training view while time steps through the sequence (the deformation
  runs every frame, as when playing);
- `adaptive`: frames while the camera orbits the scene and time plays, their size chosen
  by the viewer's `AdaptiveResolution` aiming at `--target-fps`; the side it settles at
  and the frame time there (the first `--settle` frames of each round, where it is still
  finding its size, are left out);
- `snapshot`: how long `dyngs-train --viewer`'s step hook holds training when the viewer
  asks for the model (a copy of its tensors), the longest the page can block a step.

A frame's time is `dyngs.viewer.frames.draw` (model at t, renderer, 8-bit RGB) plus the
JPEG encoding the page is sent (OpenCV, quality 90, as viser encodes it). Writes
benchmarks/results/viewer-<run name>.json with the command, commit and machine.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dyngs.tools.common import machine_info, source_commit  # noqa: E402
from dyngs.tools.view import ViewConfig, load_for_viewing  # noqa: E402
from dyngs.viewer.camera import (  # noqa: E402
    BrowserPose,
    camera_of,
    matrix_to_quaternion,
    pose_of,
    quaternion_to_matrix,
)
from dyngs.viewer.frames import Look, draw, model_summary  # noqa: E402
from dyngs.viewer.resolution import AdaptiveResolution  # noqa: E402
from dyngs.viewer.training import clone_state  # noqa: E402

SIDE = 800
JPEG_QUALITY = 90


def frame_seconds(run: Any, pose: BrowserPose, side: int, t: float) -> float:
    """Draw and encode one square frame of long side `side`; its wall time."""
    camera = camera_of(pose, side, side, run.scene.train.cameras[0])
    started = time.perf_counter()
    image = draw(run.model, run.renderer, camera, t, run.scene.background, Look())
    ok, _ = cv2.imencode(".jpg", image[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    assert ok
    return time.perf_counter() - started


def orbit(pose: BrowserPose, centre: np.ndarray, angle: float) -> BrowserPose:
    """`pose` turned by `angle` about the vertical axis through `centre` (as a mouse drag
    turns the browser's camera)."""
    c, s = math.cos(angle), math.sin(angle)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    rotation = turn @ quaternion_to_matrix(pose.wxyz)
    position = centre + turn @ (pose.position - centre)
    return BrowserPose(matrix_to_quaternion(rotation), position, pose.fov_y)


def full_round(run: Any, pose: BrowserPose, frames: int) -> list[float]:
    return [frame_seconds(run, pose, SIDE, i / max(frames - 1, 1)) for i in range(frames)]


def adaptive_round(
    run: Any, pose: BrowserPose, frames: int, target_fps: float
) -> list[tuple[int, float]]:
    """(side, seconds) of each moving frame while orbiting and playing."""
    centre = np.asarray(run.scene.scene_box.center, dtype=np.float64)
    adaptive = AdaptiveResolution(SIDE, 1.0 / target_fps)
    out = []
    for i in range(frames):
        side = adaptive.side(moving=True)
        seconds = frame_seconds(run, orbit(pose, centre, 0.05 * i), side, (0.02 * i) % 1.0)
        adaptive.measured(side, seconds)
        out.append((side, seconds))
    return out


def snapshot_seconds(run: Any, repeats: int) -> list[float]:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        clone_state(run.model)
        times.append(time.perf_counter() - started)
    return times


def summary(seconds: list[float]) -> dict[str, float]:
    ordered = sorted(seconds)
    median = statistics.median(ordered)
    return {
        "median_ms": 1e3 * median,
        "p90_ms": 1e3 * ordered[int(0.9 * (len(ordered) - 1))],
        "fps": 1.0 / median,
    }


def measure(args: argparse.Namespace) -> dict[str, Any]:
    run = load_for_viewing(ViewConfig(load_dir=args.run))
    pose = pose_of(run.scene.train.cameras[0])
    for _ in range(2):  # warm-up: compiled kernels load, caches fill
        frame_seconds(run, pose, SIDE, 0.5)
    full: list[float] = []
    moving: list[tuple[int, float]] = []
    for _ in range(args.rounds):  # interleaved, so a busy spell hits both alike
        full += full_round(run, pose, args.frames)
        moving += adaptive_round(run, pose, args.frames + args.settle, args.target_fps)[
            args.settle :
        ]
    sides = [side for side, _ in moving]
    return {
        "run": str(args.run),
        "model": model_summary(run.model),
        "renderer": type(run.renderer).__name__,
        "full": {"size": f"{SIDE}x{SIDE}", **summary(full)},
        "adaptive": {
            "target_fps": args.target_fps,
            "side_median": statistics.median(sides),
            "side_range": [min(sides), max(sides)],
            **summary([seconds for _, seconds in moving]),
        },
        "snapshot": summary(snapshot_seconds(run, 20)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="run folder (dyngs-train)")
    parser.add_argument("--frames", type=int, default=20, help="frames per round and case")
    parser.add_argument("--rounds", type=int, default=3, help="rounds, cases interleaved")
    parser.add_argument("--settle", type=int, default=10, help="adaptive frames left out")
    parser.add_argument("--target-fps", type=float, default=12.0, help="as dyngs-view's")
    parser.add_argument("--output", type=Path, help="default: results/viewer-<run>.json")
    args = parser.parse_args()
    commit = source_commit(ROOT)
    result = {
        "command": " ".join(["python", *sys.argv]),
        "commit": commit,
        "machine": machine_info(),
        "load_average": os.getloadavg(),
        "env": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS")},
        **measure(args),
    }
    result["load_average_after"] = os.getloadavg()
    output = args.output or ROOT / "benchmarks" / "results" / f"viewer-{args.run.name}.json"
    output.write_text(json.dumps(result, indent=2) + "\n")
    full, adaptive = result["full"], result["adaptive"]
    print(f"{result['model']}, {result['renderer']}, {torch.get_num_threads()} threads")
    print(f"800x800: {full['median_ms']:.0f} ms median ({full['fps']:.1f} frames/s)")
    print(f"adaptive: side {adaptive['side_median']:.0f}, {adaptive['median_ms']:.0f} ms median "
          f"({adaptive['fps']:.1f} frames/s, target {adaptive['target_fps']:g})")  # fmt: skip
    print(f"snapshot (hook): {result['snapshot']['median_ms']:.2f} ms median")
    print(f"wrote {output}")


if __name__ == "__main__":
    main()

"""The scene file every renderer adapter reads (benchmark-only; no dependency of dyngs).

An .npz of float32 arrays: means [N, 3] (world), quats [N, 4] (w, x, y, z, unnormalised),
scales [N, 3] (standard deviations), opacities [N] in [0, 1], colors [N, 3] RGB in
[0, 1]; world_to_camera [4, 4] (OpenCV: x right, y down, z forward), K [3, 3] (pixel
centres at +0.5); ints width, height. The background is black. An adapter is run as

    PYTHON ADAPTER SCENE.npz OUT.json --repeats R [--backward]

with THREADS in its environment, and writes OUT.json ({"forward_s": [...], "total_s":
[...], "version": ..., "notes": ...}) and OUT.npy (the last image, H×W×3 float32).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def adapter_args() -> argparse.Namespace:
    """An adapter's command line, as above: scene, out, --repeats, --backward."""
    parser = argparse.ArgumentParser()
    parser.add_argument("scene")
    parser.add_argument("out")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--backward", action="store_true")
    return parser.parse_args()


def load(path: str) -> dict[str, np.ndarray]:
    return dict(np.load(path))


def save_result(out: str, image: np.ndarray, result: dict) -> None:
    np.save(Path(out).with_suffix(".npy"), np.asarray(image, dtype=np.float32)[..., :3])
    Path(out).write_text(json.dumps(result, indent=1) + "\n")

"""Fit the cpu-reference tile-size cost model on trained runs, and check its choices.

    python benchmarks/calibrate_tiles.py outputs/bench/*/points/* --output FILE

Every other test view of every run is projected once and rasterised (forward, no
gradient, one thread) at tile sizes 4, 8 and 16, the best of `--repeats` timings kept.
A least-squares fit of time ≈ c + a · tile pairs + b · tile pairs · pixels per tile gives
a/b, the `_PAIR_COST` of dyngs/renderers/cpu_reference.py. The script then sums, over
all frames, the time of each fixed size, of the renderer's own per-frame choice
(`choose_tile_size`), and of the best size in hindsight. Prints the figures and writes
them to --output (JSON).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch

from dyngs.renderers import cpu_reference, stages
from dyngs.runs import load_run

SIZES = cpu_reference._TILE_SIZES


def measure(run_dir: Path, repeats: int) -> list[dict[str, float]]:
    run = load_run(run_dir)
    background = run.scene.background.to(torch.float32)
    frames = []
    with torch.no_grad():
        for view in list(run.data().views("test"))[::2]:
            camera = view.camera
            gaussians = run.model.at(view.time)
            screen = stages.project(gaussians, camera, run.renderer.guards)
            pairs = cpu_reference.tile_pair_counts(screen, camera.width, camera.height, SIZES)
            chosen = cpu_reference.choose_tile_size(screen, camera.width, camera.height)
            frame: dict[str, float] = {"chosen": chosen}
            for size, count in zip(SIZES, pairs, strict=True):
                best = float("inf")
                for _ in range(repeats):
                    started = time.perf_counter()
                    cpu_reference.rasterize(screen, camera.width, camera.height, background,
                                            guards=run.renderer.guards, tile_size=size)  # fmt: skip
                    best = min(best, time.perf_counter() - started)
                frame[f"ms_{size}"] = 1000 * best
                frame[f"pairs_{size}"] = count
            frames.append(frame)
    return frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", type=Path, nargs="+", help="trained run folders")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--output", type=Path, default=Path("benchmarks/results/tiles.json"))
    args = parser.parse_args()
    torch.set_num_threads(1)

    frames: list[dict[str, float]] = []
    per_run = {}
    for run_dir in args.runs:
        measured = measure(run_dir, args.repeats)
        frames += measured
        per_run[str(run_dir)] = {
            f"ms_{size}": sum(f[f"ms_{size}"] for f in measured) for size in SIZES
        }
        print(run_dir, {k: round(v, 1) for k, v in per_run[str(run_dir)].items()}, flush=True)

    rows = [(1.0, f[f"pairs_{s}"], f[f"pairs_{s}"] * s * s) for f in frames for s in SIZES]
    times = [f[f"ms_{s}"] for f in frames for s in SIZES]
    (const, per_pair, per_pixel), *_ = np.linalg.lstsq(np.array(rows), np.array(times), rcond=None)

    totals = {f"fixed {s}": sum(f[f"ms_{s}"] for f in frames) for s in SIZES}
    totals[f"chosen (pair cost {cpu_reference._PAIR_COST})"] = sum(
        f[f"ms_{int(f['chosen'])}"] for f in frames
    )
    totals["best in hindsight"] = sum(min(f[f"ms_{s}"] for s in SIZES) for f in frames)
    result = {
        "machine": {"platform": platform.platform(), "torch": torch.__version__, "threads": 1},
        "frames": len(frames),
        "fit_ms": {"constant": const, "per_tile_pair": per_pair, "per_pixel_pair": per_pixel},
        "pair_cost_fitted": per_pair / per_pixel,
        "total_ms": totals,
        "per_run_ms": per_run,
    }
    print(f"{len(frames)} frames; fitted pair cost {per_pair / per_pixel:.1f} pixel pairs")
    for name, total in totals.items():
        print(f"  {name:>24}: {total:8.0f} ms")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()

"""Count the work a frame of each trained run costs, independent of the machine's speed.

    python benchmarks/work_counts.py outputs/bench/importance-demo/points/* RUNS…

Render times on a shared machine drift by tens of per cent between sessions, more than
the margins a render target is decided by (docs/CAPACITY.md). The work itself does not
drift. For every view of `--split`, with the run's own renderer settings:

- `deformed`: Gaussians that query the field and the head (static ones do not);
- `visible`: Gaussians projected onto the image and binned;
- `tile_pairs`: (tile, Gaussian) pairs binning makes at the tile size the
  `cpu-reference` renderer draws that frame with;
- `pixel_pairs`: those pairs times the pixels of a tile, the Gaussian–pixel pairs that
  compositing evaluates (before padding a chunk's tiles to its busiest one).

Each is the mean over the views. Counting needs no timing, so one pass suffices.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import torch

from dyngs.renderers.cpu_reference import CpuReferenceRenderer, choose_tile_size, tile_pair_counts
from dyngs.renderers.stages import project
from dyngs.runs import LoadedRun, load_run


def count_run(run: LoadedRun, split: str) -> dict[str, object]:
    renderer = run.renderer
    if not isinstance(renderer, CpuReferenceRenderer):
        raise SystemExit(f"{run.run_dir}: counts follow the cpu-reference renderer's binning")
    config = renderer.config
    deformed = int(run.model.dynamic.sum()) if run.model.deforming else 0
    frames = []
    with torch.no_grad():
        for view in run.data().views(split):
            gaussians = run.model.at(view.time)
            camera = view.camera
            screen = project(gaussians, camera, renderer.guards, config.antialiased)
            tile = config.tile_size or choose_tile_size(screen, camera.width, camera.height)
            [pairs] = tile_pair_counts(screen, camera.width, camera.height, [tile])
            frames.append(
                {
                    "visible": int(screen.visible.sum()),
                    "tile_pairs": pairs,
                    "pixel_pairs": pairs * tile * tile,
                }
            )
    if not frames:
        raise SystemExit(f"{run.run_dir}: the {split} split has no views")
    means = {key: statistics.mean(frame[key] for frame in frames) for key in frames[0]}
    return {
        "run": str(run.run_dir),
        "views": len(frames),
        "gaussians": len(run.model.canonical),
        "deformed": deformed,
    } | means


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", type=Path, nargs="+", help="run folders (config + checkpoint)")
    parser.add_argument("--split", default="test")
    parser.add_argument("--output", type=Path, default=Path("benchmarks/results/work_counts.json"))
    args = parser.parse_args()
    rows = []
    for folder in args.runs:
        row = count_run(load_run(folder), args.split)
        rows.append(row)
        print(
            f"{folder}: {row['gaussians']} Gaussians, {row['deformed']} deformed, "
            f"{row['visible']:.0f} visible, {row['tile_pairs']:.0f} tile pairs, "
            f"{row['pixel_pairs']:.0f} pixel pairs per frame"
        )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps({"results": rows}, indent=2) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()

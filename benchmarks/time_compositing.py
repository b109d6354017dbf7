"""Time cpu-tile's compositing kernels alone, per launch, and what a pixel visit costs.

    python benchmarks/time_compositing.py --threads 1 [--demo-run RUN]

`bench_renderer.py` times whole renders, each in a fresh process, against other
renderers; this script is the quick loop for work on the kernels themselves
(`dyngs/renderers/tile_kernels.py`): it renders `bench_renderer.py`'s synthetic scenes
(and, with `--demo-run`, a trained run's test frames as `bench_renderer.py --demo-run`
draws them) in-process, forward and backward, and reports, as medians over `--repeats`
renders after a warm-up, the milliseconds spent in the forward and backward compositing
launches, the pixel visits (pixels inside a Gaussian's row spans while still
compositing) and pairs drawn that the forward kernel counts, and the thread-time per
visit, launch ms × threads ÷ visits. Edit the kernels, run it again, compare. It writes
the figures to `--output` as JSON.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_renderer import (  # noqa: E402
    SCENE_ARRAYS,
    _time_compositing,
    demo_frames,
    load_scene_file,
    make_scene,
)

from dyngs.renderers.cpu_tile import CpuTileConfig  # noqa: E402
from dyngs.tools.common import write_report  # noqa: E402
from dyngs.types import Camera, Gaussians  # noqa: E402

CASES = [("10k-128", 10_000, 128), ("50k-256", 50_000, 256)]  # (name, Gaussians, size)


def time_case(
    scene: Gaussians, camera: Camera, threads: int, repeats: int, tile_size: int | None = None
) -> dict:
    """Render one scene forward and backward `repeats` + 1 times; medians of the timed ones."""
    spent = _time_compositing()
    draw = CpuTileConfig(threads=threads, tile_size=tile_size).build()
    forward, backward = [], []
    for repeat in range(repeats + 1):
        leaves = {name: getattr(scene, name).clone().requires_grad_(True)
                  for name in SCENE_ARRAYS}  # fmt: skip
        spent.clear()
        out = draw(Gaussians(**leaves), camera, torch.zeros(3))
        (out.rgb.sum() + out.alpha.sum()).backward()
        if repeat > 0:
            forward.append(spent[0])
            backward.append(spent[1])
    work = draw.last_work  # the forward kernel's counts, per tile: visits, pairs drawn
    assert work is not None
    visits, pairs = int(work[:, 0].sum()), int(work[:, 1].sum())
    forward_ms, backward_ms = statistics.median(forward) * 1e3, statistics.median(backward) * 1e3
    return {"forward_ms": forward_ms, "backward_ms": backward_ms, "visits": visits,
            "pairs_drawn": pairs, "forward_ns_per_visit": forward_ms * 1e6 * threads / visits,
            "backward_ns_per_visit": backward_ms * 1e6 * threads / visits,
            "forward_runs_ms": [s * 1e3 for s in forward],
            "backward_runs_ms": [s * 1e3 for s in backward]}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--sigma-px", type=float, default=1.5, help="as bench_renderer.py's")
    parser.add_argument("--demo-run", type=Path, default=None,
                        help="also time this trained run's test frames")  # fmt: skip
    parser.add_argument("--demo-frames", type=int, default=5)
    parser.add_argument(
        "--tile-size", type=int, default=None, help="cpu-tile's tile size (default: per image)"
    )
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks/results/compositing.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    started = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    results = {}
    scenes = [(name, lambda n=n, size=size: make_scene(n, size, args.sigma_px))
              for name, n, size in CASES]  # fmt: skip
    if args.demo_run is not None:
        folder = Path(tempfile.mkdtemp(prefix="time-compositing-"))
        scenes += [(path.stem, lambda path=path: load_scene_file(path))
                   for path in demo_frames(args.demo_run, folder, args.demo_frames)]  # fmt: skip
    for name, build in scenes:
        r = results[name] = time_case(*build(), args.threads, args.repeats, args.tile_size)
        print(f"{name}: forward {r['forward_ms']:.2f} ms, backward {r['backward_ms']:.2f} ms, "
              f"{r['visits']:,} visits, {r['pairs_drawn']:,} pairs drawn, "
              f"{r['forward_ns_per_visit']:.1f} / {r['backward_ns_per_visit']:.1f} "
              f"thread-ns a visit")  # fmt: skip
    write_report(args.output, ROOT, args.threads, started=started, threads=args.threads,
                 sigma_px=args.sigma_px, tile_size=args.tile_size, cases=results)  # fmt: skip


if __name__ == "__main__":
    main()

"""What measuring each Gaussian's contribution costs a render, on trained models.

    python benchmarks/bench_contribution.py outputs/bench/importance-demo/points/* --threads 1

Importance pruning reads `RenderOutput.contribution`, each Gaussian's blending weight
summed over the pixels; it costs a pass over every Gaussian–pixel pair. Until `9be0e88`
every render measured it, every training step and every evaluated frame. This script
renders each run's training views as a training step does (forward and backward) and
as evaluation does (forward only, no gradient), with and without the measure,
interleaved frame by frame so that slow spells hit both alike, and reports the median
over `--repeats` passes of each pass's total time. That the image does not depend on
it is tested (tests/renderers/test_cpu_reference.py).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from dyngs.renderers.base import ContributionRenderer
from dyngs.runs import LoadedRun, load_run
from dyngs.tools.common import machine_info


def render_seconds(run: LoadedRun, view, contribution: bool, backward: bool) -> float:  # type: ignore[no-untyped-def]
    renderer = run.renderer
    if contribution and not isinstance(renderer, ContributionRenderer):
        raise SystemExit(f"{run.run_dir}: its renderer does not measure contribution")
    background = run.scene.background.to(run.device, torch.float32)
    started = time.perf_counter()
    with torch.set_grad_enabled(backward):
        gaussians = run.model.at(view.time)
        if contribution and isinstance(renderer, ContributionRenderer):
            out = renderer.with_contribution(gaussians, view.camera, background)
        else:
            out = renderer(gaussians, view.camera, background)
        if backward:
            out.rgb.sum().backward()
    seconds = time.perf_counter() - started
    run.model.zero_grad(set_to_none=True)
    return seconds


def time_run(run: LoadedRun, repeats: int, views: int) -> dict[str, object]:
    frames = list(run.data().views("train"))[:views]
    modes = [(c, b) for b in (True, False) for c in (True, False)]
    totals: dict[tuple[bool, bool], list[float]] = {mode: [] for mode in modes}
    for frame in frames[:2]:  # warm-up: allocator growth, first-call costs
        for mode in modes:
            render_seconds(run, frame, *mode)
    for _ in range(repeats):
        passes = dict.fromkeys(modes, 0.0)
        for frame in frames:
            for mode in modes:
                passes[mode] += render_seconds(run, frame, *mode)
        for mode in modes:
            totals[mode].append(passes[mode])
    row: dict[str, object] = {"run": str(run.run_dir), "views": len(frames)}
    for backward, name in ((True, "train_step"), (False, "forward")):
        with_ms = 1000 * statistics.median(totals[True, backward]) / len(frames)
        without_ms = 1000 * statistics.median(totals[False, backward]) / len(frames)
        row[name] = {
            "with_contribution_ms": with_ms,
            "without_ms": without_ms,
            "saving": 1 - without_ms / with_ms,
        }
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", type=Path, nargs="+", help="run folders (config + checkpoint)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--views", type=int, default=20, help="training views per pass")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--output", type=Path, default=Path("benchmarks/results/contribution.json"))
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    rows = []
    for folder in args.runs:
        run = load_run(folder)
        row = time_run(run, args.repeats, args.views)
        rows.append(row)
        for name in ("train_step", "forward"):
            cell = row[name]
            assert isinstance(cell, dict)
            print(
                f"{folder} {name}: {cell['with_contribution_ms']:.1f} ms with the measure, "
                f"{cell['without_ms']:.1f} ms without ({100 * cell['saving']:.0f} % saved)"
            )
    machine = machine_info()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps({"machine": machine, "results": rows}, indent=2) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()

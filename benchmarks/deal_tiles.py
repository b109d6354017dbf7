"""The compositing kernels' time with the tiles dealt to the threads in turn against
busiest first to the least loaded thread (`cpu_tile._Plan.deal`), on a training run's
frames, interleaved.

    python benchmarks/deal_tiles.py --at 1500 3000 5000 --output F -- hexplane-4dgs --data demo

Trains the `dyngs-train` command after `--` and, at each step of `--at`, draws every
`--every`-th training view of the model as it stands then, forward and backward, with
each deal in turn `--rounds` times (the order flipped from round to round). Prints and
writes to `--output` the median over rounds of each kernel's time a frame
(`dyngs.compiled.kernel_times`) and of how much the busier thread's cells exceed the
mean. The deal in turn is this script's own (a tile to each thread in turn, busiest
first, as cpu-tile dealt them before `_Plan.deal`); the image is the same either way.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from profile_step import train_command, trainer_at  # noqa: E402

from dyngs.compiled import kernel_times, thread_count  # noqa: E402
from dyngs.renderers import cpu_tile  # noqa: E402
from dyngs.tools.common import machine_info, source_commit  # noqa: E402

BY_WORK = cpu_tile._Plan.deal


def in_turn(plan: cpu_tile._Plan) -> tuple[np.ndarray, np.ndarray]:
    """The busy tiles, busiest first (by Gaussian count, ties in tile order), dealt to
    the threads in turn."""
    order = plan.busiest_first()
    threads = thread_count(plan.threads)
    return cpu_tile.grouped_by_thread(order, np.arange(len(order)) % threads, threads)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--at", type=int, nargs="+", default=[1500, 3000, 5000])
    parser.add_argument("--every", type=int, default=4, help="draw every n-th training view")
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks/results/deal-tiles.json")
    parser.add_argument("train", nargs=argparse.REMAINDER, help="-- then a dyngs-train command")
    args = parser.parse_args()
    command = train_command(args.train)
    torch.set_num_threads(args.threads)
    results = []
    with tempfile.TemporaryDirectory() as folder:
        trainer, done = trainer_at(command, 0, Path(folder)), 0
        for at in sorted(args.at):
            for step in range(done, at):
                trainer.train_step(step)
            done = at
            row = measure(trainer, args.every, args.rounds)
            row["at"] = at
            print(json.dumps(row))
            results.append(row)
    output = {
        "command": " ".join(command),
        "results": results,
        "commit": source_commit(ROOT),
        "machine": machine_info(args.threads),
    }
    args.output.write_text(json.dumps(output, indent=1) + "\n")
    print(f"wrote {args.output}")


def measure(trainer: object, every: int, rounds: int) -> dict[str, object]:
    """Median kernel ms a frame and the busier thread's excess cells, each deal."""
    renderer, data = trainer.renderer, trainer.data  # type: ignore[attr-defined]
    frames = []
    for index in range(0, data.num_train, every):
        batch = data.train_batch(index)
        with torch.no_grad():
            drawn = trainer.model.at(batch.time)  # type: ignore[attr-defined]
        leaves = {f.name: leaf(getattr(drawn, f.name)) for f in dataclasses.fields(drawn)}
        frames.append((type(drawn)(**leaves), batch.camera))
    bounds: list[np.ndarray] = []

    def recorded(deal):  # type: ignore[no-untyped-def]
        def dealt(plan: cpu_tile._Plan) -> tuple[np.ndarray, np.ndarray]:
            order, limits = deal(plan)
            bounds.append(limits)
            return order, limits

        return dealt

    deals = {"in turn": recorded(in_turn), "by work": recorded(BY_WORK)}
    times: dict[str, dict[str, list[float]]] = {name: {} for name in deals}
    excess: dict[str, list[float]] = {name: [] for name in deals}
    try:
        for round_ in range(rounds):
            for name in deals if round_ % 2 == 0 else reversed(list(deals)):
                cpu_tile._Plan.deal = deals[name]  # type: ignore[method-assign]
                with kernel_times() as launches:
                    for gaussians, camera in frames:
                        out = renderer(gaussians, camera, data.background)
                        out.rgb.sum().backward()
                        if round_ == 0:
                            excess[name].append(busiest_excess(renderer.last_work, bounds[-1]))
                for kernel in ("composite_forward", "composite_backward"):
                    per_frame = sum(launches[kernel]) / len(frames) * 1e3
                    times[name].setdefault(kernel, []).append(per_frame)
    finally:
        cpu_tile._Plan.deal = BY_WORK  # type: ignore[method-assign]
    return {
        name: {
            **{f"{k}_ms": statistics.median(v) for k, v in times[name].items()},
            "busiest_thread_excess": statistics.mean(excess[name]),
        }
        for name in deals
    } | {"frames": len(frames)}


def leaf(value: object) -> object:
    """A detached copy that asks for gradients, for a floating tensor; else the value."""
    if isinstance(value, torch.Tensor) and value.is_floating_point():
        return value.detach().clone().requires_grad_(True)
    return value


def busiest_excess(work: np.ndarray, bounds: np.ndarray) -> float:
    """How far the busiest thread's cells exceed the threads' mean (0.15: 15 %), from a
    render's per-tile counts (in its deal's order) and its deal's bounds."""
    running = np.concatenate(([0], np.cumsum(work[:, 0])))
    cells = running[bounds[1:]] - running[bounds[:-1]]
    return float(cells.max() / cells.mean() - 1.0) if cells.sum() else 0.0


if __name__ == "__main__":
    main()

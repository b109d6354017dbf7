"""Where a training step's time goes: train to a step, then profile the steps after it.

    python benchmarks/profile_step.py --at 1500 --steps 100 -- hexplane-4dgs --data demo

Everything after `--` is a `dyngs-train` command line (no run folder is written). The
script trains `--at` steps unprofiled, times `--timed` steps (the median step, wall
clock) and each compiled kernel's time in them (`dyngs.compiled.kernel_times`, timed
where it runs), then runs `--steps` steps under `torch.profiler` and prints its table of
operators by self CPU time. It writes the step time, the Gaussian count and the top
operators (self CPU ms per step, calls per step) to `--output` as JSON. Profiler
overhead inflates the profiled steps: read the table for shares, the timed median for
the step's cost. It inflates some operators far more than others (on the demo at step
1500 the head's ReLU over 7 000 × 64 rows showed about 2 ms a call, where the whole head
forward takes about 2 ms timed alone), so time an operator directly before acting on its
share.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
from rich.console import Console
from torch.profiler import ProfilerActivity, profile

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dyngs.cli import parse  # noqa: E402
from dyngs.compiled import kernel_times  # noqa: E402
from dyngs.engine.trainer import Trainer  # noqa: E402
from dyngs.engine.writer import NullWriter  # noqa: E402
from dyngs.tools.common import keep_freed_memory, machine_info, source_commit  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--at", type=int, default=1500, help="steps trained before timing")
    parser.add_argument("--timed", type=int, default=50, help="steps timed one by one")
    parser.add_argument("--steps", type=int, default=100, help="steps profiled")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--top", type=int, default=25, help="operators reported")
    parser.add_argument(
        "--output", type=Path, default=ROOT / "benchmarks/results/profile-step.json"
    )
    parser.add_argument("train", nargs=argparse.REMAINDER, help="-- then a dyngs-train command")
    args = parser.parse_args()
    command = train_command(args.train)
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as folder:
        trainer = trainer_at(command, args.at, Path(folder))
        times: list[float] = []
        optimizer_times = time_calls(trainer.optimizer, "step")
        with kernel_times() as launches:
            for step in range(args.at, args.at + args.timed):
                started = time.perf_counter()
                trainer.train_step(step)
                times.append(time.perf_counter() - started)
        optimizer_times = optimizer_times.copy()  # the profiled steps below add to the list
        first = args.at + args.timed
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            for step in range(first, first + args.steps):
                trainer.train_step(step)
        gaussians = len(trainer.model.canonical)
        dynamic = trainer.model.dynamic_fraction()
    averages = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=args.top))
    step_ms = statistics.median(times) * 1e3
    optimizer_ms = statistics.median(optimizer_times) * 1e3
    kernels = kernels_per_step(launches, args.timed)
    for name, k in kernels.items():
        print(f"{name:>28}  {k['ms']:6.3f} ms a step  ({k['calls']:.2f} calls, "
              f"median {k['median_call_ms']:.3f} ms)")  # fmt: skip
    print(
        f"step {args.at}: median {step_ms:.1f} ms over {args.timed} steps (the optimizer's "
        f"step {optimizer_ms:.2f} ms of it, the compiled kernels "
        f"{sum(k['ms'] for k in kernels.values()):.1f} ms timed in place), "
        f"{gaussians} Gaussians, {dynamic:.0%} dynamic"
    )
    result = {
        "command": " ".join(command),
        "at": args.at,
        "step_ms_median": step_ms,
        "optimizer_step_ms_median": optimizer_ms,
        "gaussians": gaussians,
        "dynamic_fraction": dynamic,
        "kernels_ms_per_step": kernels,
        "operators_self_ms_per_step": {
            e.key: {"ms": e.self_cpu_time_total / 1e3 / args.steps, "calls": e.count / args.steps}
            for e in averages[: args.top]
        },
        "commit": source_commit(ROOT),
        "machine": machine_info(args.threads),
    }
    args.output.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.output}")


def kernels_per_step(launches: dict[str, list[float]], steps: int) -> dict[str, dict[str, float]]:
    """Each compiled kernel's wall time a step (ms, the mean over `steps` steps), launches a
    step and median launch (ms), from `kernel_times`' seconds, the costliest first."""
    rows = {
        name: {
            "ms": sum(seconds) * 1e3 / steps,
            "calls": len(seconds) / steps,
            "median_call_ms": statistics.median(seconds) * 1e3,
        }
        for name, seconds in launches.items()
    }
    return dict(sorted(rows.items(), key=lambda row: -row[1]["ms"]))


def train_command(train: list[str]) -> list[str]:
    """The dyngs-train command after a script's own arguments, without its `--`."""
    return train[1:] if train[:1] == ["--"] else train


def trainer_at(command: list[str], at: int, folder: Path) -> Trainer:
    """A trainer for the dyngs-train `command`, with dyngs-train's memory settings, trained
    `at` steps; it writes nothing but scratch files in `folder`."""
    keep_freed_memory()  # as dyngs-train does
    config, _ = parse(command)
    trainer = Trainer(config, folder, NullWriter(), Console(quiet=True))
    for step in range(at):
        trainer.train_step(step)
    return trainer


def time_calls(owner: object, name: str) -> list[float]:
    """Wrap `owner.name` so that each call's wall time (seconds) is appended to the list
    returned; the calls themselves are unchanged."""
    inner = getattr(owner, name)
    seconds: list[float] = []

    def timed(*args: object, **kwargs: object) -> object:
        started = time.perf_counter()
        result = inner(*args, **kwargs)
        seconds.append(time.perf_counter() - started)
        return result

    setattr(owner, name, timed)
    return seconds


if __name__ == "__main__":
    main()

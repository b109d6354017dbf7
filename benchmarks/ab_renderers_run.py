"""Two whole training runs, one per renderer, stepped in turn in one process: the end-to-end
speed ratio of two renderers, held steady against a machine whose speed drifts.

    python benchmarks/ab_renderers_run.py --threads 2 --output benchmarks/results/ab-run.json \
        -- hexplane-4dgs --data demo --seed 1

Everything after `--` is a `dyngs-train` command line without a renderer (no run folder is
kept). The script builds one trainer for it with `renderer:cpu-tile` and one with
`renderer:cpu-reference` (`--renderers` changes the pair) and runs their steps
alternately, A's step s, then B's, until both have trained the command's steps. Each
step's wall time counts to its run, as `dyngs-train`'s train_seconds counts it, the
lifecycle's refinements and importance passes included. Then each run finishes and is
evaluated as `dyngs-train` does. It writes both runs' training seconds, their ratio and
their test PSNR to `--output` as JSON.

Why one process: on the machines this project measures on, two runs of the same command
minutes apart differed by up to 26 % (docs/RENDERER.md), more than the change a
renderer's speed-up is judged by. Alternated step by step, a slow spell of the machine
falls on both runs alike. The two runs share the process's random number generators'
calls no more than two separate runs would: each trainer draws from its own generators.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import torch
from rich.console import Console

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from profile_step import train_command, trainer_at  # noqa: E402

from dyngs.engine import schedules  # noqa: E402
from dyngs.engine.trainer import Trainer  # noqa: E402
from dyngs.tools.common import machine_info, source_commit  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--renderers", nargs=2, default=["cpu-tile", "cpu-reference"])
    parser.add_argument(
        "--output", type=Path, default=ROOT / "benchmarks/results/ab-renderers-run.json"
    )
    parser.add_argument("train", nargs=argparse.REMAINDER, help="-- then a dyngs-train command")
    args = parser.parse_args()
    command = train_command(args.train)
    torch.set_num_threads(args.threads)
    console = Console()
    with tempfile.TemporaryDirectory() as folder:
        trainers = {name: trainer(command, name, Path(folder)) for name in args.renderers}
        seconds = alternate(trainers, console)
        results = {name: finish(trainer) for name, trainer in trainers.items()}
    first, second = args.renderers
    report = {
        "command": " ".join(command),
        "renderers": args.renderers,
        "steps": next(iter(trainers.values())).config.steps,
        "train_seconds": seconds,
        "ratio": seconds[second] / seconds[first],
        "test": results,
        "commit": source_commit(ROOT),
        "machine": machine_info(args.threads),
    }
    for name in args.renderers:
        console.print(f"{name}: {seconds[name]:.1f} s of training, test PSNR "
                      f"{results[name]['psnr']:.4f} dB")  # fmt: skip
    console.print(f"{second} / {first}: {report['ratio']:.3f}×")
    args.output.write_text(json.dumps(report, indent=1) + "\n")
    console.print(f"wrote {args.output}")


def trainer(command: list[str], renderer: str, folder: Path) -> Trainer:
    """An untrained trainer for the dyngs-train `command` with `renderer`, its run folder
    in `folder` (`profile_step.trainer_at`, at step 0)."""
    return trainer_at([*command, f"renderer:{renderer}"], 0, folder / renderer)


def alternate(trainers: dict[str, Trainer], console: Console) -> dict[str, float]:
    """Every trainer's steps, one step of each in turn; each one's summed step seconds."""
    steps = max(trainer.config.steps for trainer in trainers.values())
    seconds = dict.fromkeys(trainers, 0.0)
    for step in range(steps):
        for name, trainer in trainers.items():
            if step >= trainer.config.steps:
                continue
            started = time.perf_counter()
            trainer.train_step(step)
            trainer.step = step + 1
            seconds[name] += time.perf_counter() - started
        if (step + 1) % 500 == 0 or step + 1 == steps:
            console.print(f"step {step + 1}/{steps}  " + "  ".join(
                f"{name} {total:.1f} s" for name, total in seconds.items()))  # fmt: skip
    return seconds


def finish(trainer: Trainer) -> dict[str, float]:
    """The run's end as `Trainer.train` has it, then its evaluation: PSNR, SSIM, count."""
    trainer.model.deforming = schedules.deforming(trainer.config, trainer.step)
    trainer.lifecycle.finish(trainer.step, trainer.optimizer)
    metrics = trainer.evaluate()
    return {key: metrics[key] for key in ("psnr", "ssim", "num_gaussians")}


if __name__ == "__main__":
    main()

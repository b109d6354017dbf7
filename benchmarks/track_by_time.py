"""Follow a training run's fit by time: does the deformation keep up with the time window?

    python benchmarks/track_by_time.py --every 100 --output FILE -- hexplane-4dgs --seed 1

Trains the configuration that `dyngs-train` would build from the arguments after `--`
(nothing is written but --output) and, every `--every` steps from the end of the
warm-up on, renders every training view and prints the mean PSNR of each of `--bins`
equal spans of t, beside the step and the time window. A span that stays low after the
window has passed it is motion the deformation lost. The table goes to --output (JSON).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from dyngs.engine import schedules
from dyngs.engine.trainer import Trainer
from dyngs.engine.writer import NullWriter
from dyngs.metrics import psnr
from dyngs.runs import expand_argument_files, parse_train_args

_spec = importlib.util.spec_from_file_location(
    "psnr_by_time", Path(__file__).with_name("psnr_by_time.py")
)
assert _spec is not None and _spec.loader is not None
_psnr_by_time = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_psnr_by_time)
by_time = _psnr_by_time.by_time


def fit_by_time(trainer: Trainer, bins: int) -> list[float | None]:
    """Mean PSNR of the training views in each of `bins` spans of t, as the model is now."""
    frames = []
    with torch.no_grad():
        for view in trainer.data.views("train"):
            gaussians = trainer.model.at(view.time)
            rgb = trainer.renderer(gaussians, view.camera, trainer.data.background).rgb.clamp(0, 1)
            frames.append({"time": view.time, "psnr": float(psnr(rgb, view.image))})
    return by_time(frames, bins)


def track(trainer: Trainer, every: int, bins: int) -> list[dict[str, Any]]:
    """Train to the end, measuring `fit_by_time` every `every` steps after the warm-up."""
    rows: list[dict[str, Any]] = []
    started = time.perf_counter()
    while trainer.step < trainer.config.steps:
        trainer.train_step(trainer.step)
        trainer.step += 1
        if trainer.step % every == 0 and schedules.deforming(trainer.config, trainer.step):
            row: dict[str, Any] = {
                "step": trainer.step,
                "window": schedules.time_window(trainer.config, trainer.step),
                "gaussians": len(trainer.model.canonical),
                "psnr_by_time": fit_by_time(trainer, bins),
            }
            rows.append(row)
            cells = " ".join(f"{p:5.1f}" if p is not None else "    -" for p in row["psnr_by_time"])
            print(
                f"{row['step']:6d}  window {row['window']:.2f}  {row['gaussians']:7,d}  {cells}"
                f"  ({time.perf_counter() - started:.0f} s)",
                flush=True,
            )
    return rows


def main() -> None:
    argv = sys.argv[1:]
    split = argv.index("--") if "--" in argv else len(argv)
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--every", type=int, default=100)
    parser.add_argument("--bins", type=int, default=10)
    parser.add_argument("--output", type=Path)
    args = parser.parse_args(argv[:split])
    if args.every < 1 or args.bins < 1:
        parser.error("--every and --bins must be ≥ 1")
    train_args = expand_argument_files(argv[split + 1 :] or ["hexplane-4dgs"])
    config = parse_train_args(train_args)
    with tempfile.TemporaryDirectory() as scratch:
        trainer = Trainer(config, Path(scratch), NullWriter())
        edges = [f"{i / args.bins:.1f}" for i in range(args.bins)]
        print(
            f"{'step':>6}  {'window':>11}  {'Gaussians':>7}  " + " ".join(f"{e:>5}" for e in edges)
        )
        rows = track(trainer, args.every, args.bins)
    if args.output:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        payload = {"train_args": train_args, "bins": args.bins, "rows": rows}
        args.output.write_text(json.dumps(payload, indent=2) + "\n")
        print(f"wrote {args.output}")


if __name__ == "__main__":
    main()

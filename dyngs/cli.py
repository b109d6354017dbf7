"""`dyngs-train`: train a preset on a dataset, e.g. `dyngs-train hexplane-4dgs --data PATH`.

Any component can be swapped on the command line (`renderer:cuda-tile`, `field:mlp`) and
flags may follow subcommands. Arguments of the form `@FILE` are replaced by the flags in
FILE (one or more per line, `#` starts a comment); configs/ holds such override files.
`dyngs-train --resume RUN` continues a run from its folder alone.
"""

from __future__ import annotations

import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import tyro
from rich.console import Console
from rich.table import Table

from dyngs.config import TrainConfig
from dyngs.configio import load_config, save_config
from dyngs.engine.trainer import CHECKPOINT_NAME, Trainer
from dyngs.engine.writer import NullWriter, TensorBoardWriter, Writer
from dyngs.errors import ConfigError
from dyngs.io import write_json
from dyngs.methods import method_presets
from dyngs.tools.common import run_tool


def expand_argument_files(args: Sequence[str]) -> list[str]:
    out: list[str] = []
    for arg in args:
        if arg.startswith("@") and len(arg) > 1:
            path = Path(arg[1:])
            if not path.is_file():
                raise ConfigError(f"{path}: argument file does not exist")
            for line in path.read_text().splitlines():
                out += shlex.split(line, comments=True)
        else:
            out.append(arg)
    return out


def parse_train_args(args: Sequence[str]) -> TrainConfig:
    presets, descriptions = method_presets()
    return tyro.cli(
        tyro.extras.subcommand_type_from_defaults(presets, descriptions),
        args=expand_argument_files(args),
        prog="dyngs-train",
        description=__doc__,
        config=(tyro.conf.CascadeSubcommandArgs,),
    )


def new_run_dir(config: TrainConfig) -> Path:
    dataset = "demo" if config.data == "demo" else Path(config.data).resolve().name
    name = config.run_name or f"{config.method}-{dataset}-{time.strftime('%Y%m%d-%H%M%S')}"
    run_dir = config.output_dir / name
    if (run_dir / CHECKPOINT_NAME).exists():
        raise ConfigError(
            f"{run_dir}: this run already has a checkpoint; continue it with "
            f"`dyngs-train --resume {run_dir}` or choose another --run-name"
        )
    run_dir.mkdir(parents=True, exist_ok=True)
    return run_dir


SUMMARY_KEYS = (
    "psnr",
    "ssim",
    "lpips",
    "render_ms",
    "num_gaussians",
    "train_seconds",
    "iterations",
)


def _format(value: object) -> str:
    if value is None:
        return "null"
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def summary_table(metrics: dict) -> Table:
    table = Table(title=f"{metrics.get('split', 'test')} metrics")
    for key in SUMMARY_KEYS:
        table.add_column(key)
    table.add_row(*(_format(metrics.get(key)) for key in SUMMARY_KEYS))
    return table


def run_training(
    config: TrainConfig, run_dir: Path, console: Console, resume: bool = False
) -> dict:
    writer: Writer = (
        TensorBoardWriter(run_dir / "tensorboard") if config.tensorboard else NullWriter()
    )
    try:
        trainer = Trainer(config, run_dir, writer, console)
        if resume:
            trainer.load(run_dir / CHECKPOINT_NAME)
            console.print(f"resuming {run_dir} at step {trainer.step}")
        else:
            save_config(run_dir / "config.json", trainer.config)  # with data-sized values
        metrics = trainer.train()
        write_json(run_dir / "metrics.json", metrics)
    finally:
        writer.close()
    console.print(summary_table(metrics))
    console.print(f"run folder: {run_dir}")
    return metrics


def main(argv: Sequence[str] | None = None) -> None:
    args = list(sys.argv[1:] if argv is None else argv)

    def body(console: Console) -> None:
        if args[:1] == ["--resume"]:
            if len(args) != 2:
                raise ConfigError("usage: dyngs-train --resume RUN_FOLDER")
            run_dir = Path(args[1])
            config = load_config(run_dir / "config.json")
            if not (run_dir / CHECKPOINT_NAME).exists():
                raise ConfigError(f"{run_dir / CHECKPOINT_NAME}: no checkpoint to resume from")
            run_training(config, run_dir, console, resume=True)
        else:
            config = parse_train_args(args)
            run_training(config, new_run_dir(config), console)

    run_tool(body)


if __name__ == "__main__":
    main()

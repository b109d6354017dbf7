"""`dyngs-train`: train a preset on a dataset, e.g. `dyngs-train hexplane-4dgs --data PATH`.

Any component can be swapped on the command line (`renderer:cuda-tile`, `field:mlp`) and
flags may follow subcommands. Arguments of the form `@FILE` are replaced by the flags in
FILE (one or more per line, `#` starts a comment); configs/ holds such override files.
`dyngs-train --resume RUN` continues a run from its folder alone.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console
from rich.table import Table

from dyngs.configio import load_config
from dyngs.engine.trainer import CHECKPOINT_NAME
from dyngs.errors import ConfigError
from dyngs.runs import join_group, new_run_dir, parse_train_args, run_training
from dyngs.tools.common import run_tool

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
            group = join_group(config)  # under torchrun: data-parallel (docs/DISTRIBUTED.md)
            metrics = run_training(config, run_dir, console, resume=True, group=group)
        else:
            config = parse_train_args(args, description=__doc__)
            group = join_group(config)
            run_dir = group.decide(lambda: new_run_dir(config))  # rank 0 names it
            metrics = run_training(config, run_dir, console, group=group)
        if group.is_main:
            console.print(summary_table(metrics))
            console.print(f"run folder: {run_dir}")
        group.close()

    run_tool(body)


if __name__ == "__main__":
    main()

"""`dyngs-train`: train a preset on a dataset, e.g. `dyngs-train hexplane-4dgs --data PATH`.

Any component can be swapped on the command line (`renderer:cuda-tile`, `field:mlp`) and
flags may follow subcommands. Arguments of the form `@FILE` are replaced by the flags in
FILE (one or more per line, `#` starts a comment); configs/ holds such override files.
`dyngs-train --resume RUN` continues a run from its folder alone.

`--viewer` serves the interactive viewer (as dyngs-view) of the model while it trains, at
localhost:8080 (`--viewer-port N`, `--viewer-host H`); its page can pause training. When
training ends on a terminal, the viewer shows the final model until Ctrl-C.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from rich.console import Console
from rich.table import Table

from dyngs.config import TrainConfig
from dyngs.configio import load_config
from dyngs.engine.trainer import CHECKPOINT_NAME
from dyngs.errors import ConfigError
from dyngs.runs import join_group, new_run_dir, parse_train_args, run_training
from dyngs.tools.common import run_tool
from dyngs.viewer.options import ViewerOptions, check_port

if TYPE_CHECKING:
    from dyngs.viewer.live import LiveViewer

VIEWER_FLAGS = ("--viewer", "--viewer-port", "--viewer-host")

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


def split_viewer_args(args: Sequence[str]) -> tuple[ViewerOptions | None, list[str]]:
    """Take `--viewer`, `--viewer-port N` and `--viewer-host H` (or `--flag=value`) out
    of the arguments: the viewer is not part of the training config (nor of config.json).
    A port or host alone also asks for the viewer."""
    rest: list[str] = []
    found: dict[str, str] = {}
    items = iter(args)
    for arg in items:
        name, equals, value = arg.partition("=")
        if name not in VIEWER_FLAGS:
            rest.append(arg)
        elif name == "--viewer":
            found["on"] = ""
        else:
            value = value if equals else next(items, "")
            if not value or value.startswith("--"):
                raise ConfigError(f"{name} needs a value")
            found[name] = value
    if not found:
        return None, rest
    try:
        port = int(found.get("--viewer-port", ViewerOptions.port))
    except ValueError:
        raise ConfigError(f"--viewer-port must be a number, got {found['--viewer-port']}") from None
    return ViewerOptions(host=found.get("--viewer-host", ViewerOptions.host), port=port), rest


def parse(args: list[str]) -> tuple[TrainConfig, Path | None]:
    """The training config the arguments ask for and, with `--resume`, the run folder."""
    if args[:1] == ["--resume"]:
        if len(args) != 2:
            raise ConfigError("usage: dyngs-train --resume RUN_FOLDER")
        run_dir = Path(args[1])
        config = load_config(run_dir / "config.json")
        if not (run_dir / CHECKPOINT_NAME).exists():
            raise ConfigError(f"{run_dir / CHECKPOINT_NAME}: no checkpoint to resume from")
        return config, run_dir
    return parse_train_args(args, description=__doc__), None


def live_viewer(options: ViewerOptions | None, console: Console) -> LiveViewer | None:
    """The `--viewer` step hook; its port is checked now, not after the first step."""
    if options is None:
        return None
    check_port(options.host, options.port)
    from dyngs.viewer.live import LiveViewer  # the web server loads only when used

    return LiveViewer(options, console)


def main(argv: Sequence[str] | None = None) -> None:
    given = list(sys.argv[1:] if argv is None else argv)

    def body(console: Console) -> None:
        options, args = split_viewer_args(given)
        config, resume = parse(args)
        group = join_group(config)  # under torchrun: data-parallel (docs/DISTRIBUTED.md)
        # The process that reports (rank 0) serves the viewer; its port is checked before
        # any training.
        viewer = live_viewer(options, console) if group.is_main else None
        try:
            run_dir = resume or group.decide(lambda: new_run_dir(config))  # rank 0 names it
            hooks = [] if viewer is None else [viewer]
            metrics = run_training(config, run_dir, console, resume is not None, hooks, group)
            if group.is_main:
                console.print(summary_table(metrics))
                console.print(f"run folder: {run_dir}")
            if viewer is not None:
                viewer.finished(run_dir)
                viewer.wait_if_interactive()
        finally:
            if viewer is not None:
                viewer.close()
            # Failed runs too: a process that exits with its group still up can be killed
            # by SIGABRT as the interpreter tears down gloo's threads ("terminate called
            # without an active exception"), turning exit code 2 into -6 at random.
            group.close()

    run_tool(body)


if __name__ == "__main__":
    main()

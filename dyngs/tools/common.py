"""What every dyngs-* tool shares: the one-line error wrapper, and the machine and commit
a benchmark ran on. Run folders are loaded by `dyngs.runs.load_run`."""

from __future__ import annotations

import platform
import subprocess
import sys
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch
from rich.console import Console
from rich.markup import escape

from dyngs.errors import UserError


def machine_info(threads: int | None = None) -> dict[str, Any]:
    """What a benchmark ran on, for its results file: platform, processor (the machine
    type where the OS names none), PyTorch version and CPU threads (`threads`, else
    PyTorch's current count)."""
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "torch": torch.__version__,
        "threads": threads or torch.get_num_threads(),
    }


def source_commit(root: Path) -> str:
    """The short hash of the commit checked out at `root`, for a results file ("" where
    `root` is not a git checkout)."""
    done = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root,
                          capture_output=True, text=True)  # fmt: skip
    return done.stdout.strip()


@contextmanager
def one_line_warnings(console: Console) -> Iterator[None]:
    """Print warnings as one yellow line each (no file and line number) while active."""
    previous = warnings.showwarning
    warnings.showwarning = lambda message, *_, **__: console.print(
        f"[yellow]warning:[/yellow] {message}", highlight=False, soft_wrap=True
    )
    try:
        yield
    finally:
        warnings.showwarning = previous


def run_tool(body: Callable[[Console], object]) -> None:
    """Run a tool's body; a `UserError` becomes one red line and exit code 2, Ctrl-C 130."""
    console = Console()
    with one_line_warnings(console):
        try:
            body(console)
        except KeyboardInterrupt:
            sys.exit(130)
        except UserError as error:
            # escaped: a message may hold brackets (paths, addresses) that are not markup
            console.print(
                f"[red]error:[/red] {escape(str(error))}", highlight=False, soft_wrap=True
            )
            sys.exit(2)

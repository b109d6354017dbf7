"""The progress bar shown while datasets load or render, and the line saying what loaded."""

from __future__ import annotations

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn


def progress_bar() -> Progress:
    """A transient bar on stderr, shown only on a terminal (logs and CI stay clean)."""
    console = Console(stderr=True)
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
        disable=not console.is_terminal,
    )


def report(message: str) -> None:
    """One line on stderr (kept in logs too, unlike the bar)."""
    Console(stderr=True).print(message, highlight=False, soft_wrap=True)

"""What every dyngs-* tool shares: the one-line error wrapper, the process's memory
settings, and the machine and commit a benchmark ran on. Run folders are loaded by
`dyngs.runs.load_run`."""

from __future__ import annotations

import ctypes
import ctypes.util
import json
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
    type where the OS names none), the CPU's model as Linux names it, the vector
    instructions PyTorch uses, PyTorch version and CPU threads (`threads`, else PyTorch's
    current count).

    Two machines that both called themselves "AMD EPYC" ran the same code 1.8× apart, and
    trained the same commit and seed to different digits in some runs (docs/TRAINING.md):
    the model and the instruction set say which machine a figure belongs to."""
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu": cpu_model(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "torch": torch.__version__,
        "threads": threads or torch.get_num_threads(),
    }


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The first CPU's "model name, family F model M" from Linux's cpuinfo; "" elsewhere."""
    try:
        text = cpuinfo.read_text()
    except OSError:
        return ""
    fields: dict[str, str] = {}
    for line in text.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    name = fields.get("model name", "")
    if "cpu family" in fields and "model" in fields:
        name += f", family {fields['cpu family']} model {fields['model']}"
    return name


def source_commit(root: Path) -> str:
    """The short hash of the commit checked out at `root`, for a results file ("" where
    `root` is not a git checkout)."""
    done = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root,
                          capture_output=True, text=True)  # fmt: skip
    return done.stdout.strip()


def write_report(output: Path, root: Path, threads: int, /, **figures: Any) -> None:
    """Write a benchmark's `figures` to `output` as JSON, after the command that made them,
    the commit checked out at `root` and the machine (`machine_info`), and say where.
    The first three are positional only, so that `figures` may hold a `threads` of its own."""
    report = {
        "command": " ".join(sys.argv),
        "commit": source_commit(root),
        "machine": machine_info(threads),
        **figures,
    }
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {output}")


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


# glibc's mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
KEEP_FREED_BYTES = 256 * 2**20
"""Freed memory a dyngs process keeps mapped for its next allocations (`keep_freed_memory`)."""
MMAP_THRESHOLD_BYTES = 32 * 2**20
"""Allocations at least this large get pages of their own, returned to the system when
freed (glibc's own ceiling for its adaptive threshold on 64-bit machines)."""


def keep_freed_memory() -> bool:
    """Let this process reuse the memory it frees rather than hand it back to the system
    at once; True where the C library took the settings (glibc), False elsewhere.

    A training step or a render allocates and frees the same few megabytes of tensors and
    arrays again and again. By default glibc returns a freed block of more than 128 KiB
    (or a heap whose free top exceeds twice that) to the system, so the next step takes
    the same memory back one page fault at a time: 427 faults a frame for cpu-tile on the
    demo, 6 865 for cpu-reference, and a fault costs microseconds in a virtual machine
    (docs/RENDERER.md). Raising the two thresholds keeps up to `KEEP_FREED_BYTES` of freed
    memory mapped for reuse; the peak a process reaches is unchanged, it only stays
    mapped. PyTorch's own performance guide asks for the same with a different allocator
    (jemalloc or tcmalloc), which dyngs cannot install for its users."""
    name = ctypes.util.find_library("c")
    try:
        mallopt = ctypes.CDLL(name).mallopt if name else None
    except (OSError, AttributeError):
        mallopt = None
    if mallopt is None:
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    kept = mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
    return bool(kept and mallopt(_M_TRIM_THRESHOLD, KEEP_FREED_BYTES))


def run_tool(body: Callable[[Console], object]) -> None:
    """Run a tool's body; a `UserError` becomes one red line and exit code 2, Ctrl-C 130.
    Freed memory is kept for reuse (`keep_freed_memory`)."""
    keep_freed_memory()
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

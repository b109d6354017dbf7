"""Files that are never half written: a crash or a kill mid-write leaves the old file or
the new one, never a broken one. Every file dyngs writes into a run folder goes through
here (checkpoints, configs, metrics, scene descriptions)."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any


def atomic_write_bytes(path: Path, write: Callable[[IO[bytes]], object]) -> None:
    """Call `write(file)` on a temporary file next to `path`, fsync it, then rename it
    over `path` (atomic on POSIX) and fsync the folder so the rename itself is durable."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, lambda f: f.write(text.encode()))


def write_json(path: Path, data: Any) -> None:
    """Atomic, indented, strict JSON (a NaN or inf is a bug, not a value to write)."""
    atomic_write_text(path, json.dumps(data, indent=2, allow_nan=False) + "\n")

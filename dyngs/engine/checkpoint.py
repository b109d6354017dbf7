"""Checkpoints, written atomically (`dyngs.io`): a crash or a kill mid-write never leaves
a broken file behind."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from dyngs.errors import ConfigError
from dyngs.io import atomic_write_bytes


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    atomic_write_bytes(path, lambda f: torch.save(payload, f))


def load_checkpoint(path: Path, device: torch.device | str = "cpu") -> dict[str, Any]:
    try:
        return torch.load(path, map_location=device, weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as error:  # a truncated or foreign file: say which, in one line
        raise ConfigError(
            f"{path}: not a readable dyngs checkpoint ({type(error).__name__}: {error})"
        ) from error

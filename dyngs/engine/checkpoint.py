"""Checkpoints, written atomically (`dyngs.io`): a crash or a kill mid-write never leaves
a broken file behind."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from dyngs.errors import ConfigError
from dyngs.io import atomic_write_bytes
from dyngs.types import SceneBox


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


def upgrade_checkpoint(state: dict[str, Any], box: SceneBox, deforming: bool) -> None:
    """Bring a checkpoint written before the model kept its own state (dyngs < 0.2) to
    today's layout, in place: the SH degree, the deformation flag and the scene box go
    into the model's state; the counters and densification statistics into their own
    entries. `box` and `deforming` are what the trainer then kept itself."""
    model = state["model"]
    if "_extra_state" not in model:
        model["_extra_state"] = {
            "active_sh_degree": int(state.get("active_sh", 0)),
            "deforming": deforming,
            "box": [list(box.lower), list(box.upper)],
        }
    if "counters" not in state:
        names = ("train_seconds", "deformation_seconds", "skipped_steps")
        state["counters"] = {name: state[name] for name in names if name in state}
    if "lifecycle" not in state:
        state["lifecycle"] = {
            "densify": state["densify"],
            "importance_seconds": state.get("importance_seconds", 0.0),
        }

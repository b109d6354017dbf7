"""Checkpoints, written atomically (`dyngs.io`): a crash or a kill mid-write never leaves
a broken file behind."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from dyngs.engine import schedules
from dyngs.engine.optim import build_optimizer
from dyngs.errors import ConfigError
from dyngs.io import atomic_write_bytes
from dyngs.types import SceneBox

if TYPE_CHECKING:  # the trainer calls these with itself
    from dyngs.engine.trainer import Trainer


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


def training_state(trainer: Trainer) -> dict[str, Any]:
    """What a resumed run needs to go on bit for bit: the step, the counters, the model,
    the optimizer, the lifecycle's statistics, the data order and the random states."""
    return {
        "step": trainer.step,
        "counters": trainer.counters.state_dict(),
        "model": trainer.model.state_dict(),
        "optimizer": trainer.optimizer.state_dict(),
        "lifecycle": trainer.lifecycle.state_dict(),
        "data": trainer.data.state_dict(),
        "generator": trainer.generator.get_state(),
        "torch_rng": torch.get_rng_state(),
        "planned_steps": trainer.config.steps,
        "pace": trainer.config.pace,
        "budget": None if trainer.budget is None else trainer.budget.state_dict(),
    }


def restore_training(trainer: Trainer, state: dict[str, Any]) -> None:
    """Put `training_state`'s `state` back into `trainer`."""
    trainer.step = int(state["step"])
    deforming = schedules.deforming(trainer.config, trainer.step)
    upgrade_checkpoint(state, trainer.model.box, deforming)
    trainer.model.load_state_dict(state["model"])
    # The parameters were replaced to fit the checkpoint's Gaussian count: rebuild the
    # optimizer around them before restoring its moments.
    trainer.optimizer = build_optimizer(trainer.model, trainer.config.optim, trainer.extent)
    trainer.optimizer.load_state_dict(state["optimizer"])
    trainer.lifecycle.load_state_dict(state["lifecycle"])
    trainer.data.load_state_dict(state["data"])
    trainer.generator.set_state(state["generator"].cpu())
    torch.set_rng_state(state["torch_rng"].cpu())
    trainer.counters.load_state_dict(state["counters"])
    if trainer.budget is not None and state.get("budget") is not None:
        trainer.budget.load_state_dict(state["budget"])  # and go on with the plan it had
        pace = state.get("pace")
        trainer.lifecycle.config = dataclasses.replace(
            trainer.config,
            max_iters=int(state["planned_steps"]),
            pace=None if pace is None else (int(pace[0]), float(pace[1]), int(pace[2])),
        )
    trainer.objective.on_topology()

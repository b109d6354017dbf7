"""What every dyngs-* tool shares: the one-line error wrapper and loading a run folder.

A run folder (written by `dyngs-train`) holds `config.json` and `checkpoint.pt`; from
those alone `load_run` rebuilds the scene, the model at its last step and the renderer.
"""

from __future__ import annotations

import dataclasses
import platform
import sys
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from rich.console import Console

from dyngs.config import TrainConfig
from dyngs.configio import load_config
from dyngs.datamanagers.base import SceneData
from dyngs.datamanagers.datamanager import DataManager
from dyngs.engine.trainer import CHECKPOINT_NAME, Trainer
from dyngs.engine.writer import NullWriter
from dyngs.errors import ConfigError, UserError
from dyngs.model import DynamicGaussians
from dyngs.renderers import RENDERERS, renderer_name
from dyngs.renderers.base import Renderer


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
            console.print(f"[red]error:[/red] {error}", highlight=False, soft_wrap=True)
            sys.exit(2)


@dataclass(frozen=True)
class RunOverrides:
    """Changes to how a run folder is loaded (all optional)."""

    device: str | None = None
    """Device to load onto (`cpu`, `cuda`, …); default: the one the run was trained with."""
    renderer: str = "run"
    """Renderer to draw with: `run` (the one trained with) or a registered one
    (`cpu-reference`, `cuda-tile`, or one an installed package adds)."""

    def __post_init__(self) -> None:
        if self.renderer != "run" and self.renderer not in RENDERERS:
            known = ", ".join(["run", *RENDERERS.names()])
            raise ConfigError(f"--renderer must be one of {known}, got {self.renderer!r}")
    data: str | None = None
    """Dataset folder, when it has moved since training (default: the run's `--data`)."""


@dataclass(frozen=True)
class LoadedRun:
    """A trained run, ready to render: model at its checkpoint, its scene and renderer."""

    run_dir: Path
    config: TrainConfig
    """The run's resolved config, with any `RunOverrides` applied."""
    model: DynamicGaussians
    renderer: Renderer
    data: DataManager
    device: torch.device
    step: int
    """Training iterations done when the checkpoint was written."""
    train_seconds: float
    sh_degree: int
    """SH degree active at `step` (what training drew with)."""
    deform: bool
    """Whether the deformation field was on at `step` (off during the static warm-up)."""

    @property
    def scene(self) -> SceneData:
        return self.data.scene


def load_run(
    run_dir: Path | str,
    device: str | torch.device | None = None,
    overrides: RunOverrides | None = None,
    console: Console | None = None,
) -> LoadedRun:
    """Rebuild a run from its folder (config.json + checkpoint.pt).

    `device` (or `overrides.device`) moves it to another device; a missing or broken
    folder is a one-line `ConfigError` naming the path.
    """
    run_dir = Path(run_dir)
    overrides = overrides or RunOverrides()
    if not run_dir.is_dir():
        raise ConfigError(f"{run_dir}: no such run folder")
    config_path = run_dir / "config.json"
    try:
        config = load_config(config_path)
    except (KeyError, TypeError, ValueError, ImportError, AttributeError) as error:
        raise ConfigError(
            f"{config_path}: not a dyngs run config ({type(error).__name__}: {error})"
        ) from None
    if not isinstance(config, TrainConfig):
        raise ConfigError(f"{config_path}: not a dyngs training config")
    changes: dict[str, Any] = {}
    if device is not None or overrides.device is not None:
        changes["device"] = str(device if device is not None else overrides.device)
    if overrides.renderer not in ("run", renderer_name(config.renderer)):
        changes["renderer"] = RENDERERS.get(overrides.renderer)()
    if overrides.data is not None:
        changes["data"] = overrides.data
    config = dataclasses.replace(config, **changes)
    checkpoint = run_dir / CHECKPOINT_NAME
    if not checkpoint.is_file():
        raise ConfigError(f"{checkpoint}: no checkpoint (has this run saved one yet?)")
    trainer = Trainer(config, run_dir, NullWriter(), console)
    try:
        trainer.load(checkpoint)
    except (KeyError, RuntimeError, ValueError) as error:
        first_line = str(error).strip().splitlines()[0] if str(error).strip() else ""
        raise ConfigError(
            f"{checkpoint}: does not fit {config_path} ({type(error).__name__}: {first_line})"
        ) from None
    trainer.model.eval()
    return LoadedRun(
        run_dir=run_dir,
        config=config,
        model=trainer.model,
        renderer=trainer.renderer,
        data=trainer.data,
        device=trainer.device,
        step=trainer.step,
        train_seconds=trainer.train_seconds,
        sh_degree=trainer.active_sh,
        deform=trainer.deforming(trainer.step),
    )

"""Run folders: training into one, and loading one back.

A run folder (OUTPUT_DIR/RUN_NAME) holds:
- `config.json`: the resolved config (data-sized values filled in), `dyngs.configio`;
- `scene.json`: every view's camera and time, the box and the background
  (`dyngs.datamanagers.scene_info`);
- `checkpoint.pt`: the model, optimizer, lifecycle, data order and random state;
- `metrics.json`, `tensorboard/`, and the rendered test views.

From config.json, scene.json and checkpoint.pt alone `load_run` rebuilds the trained
model and its renderer: rendering and exporting need no dataset. Evaluating reads the
images again (`LoadedRun.data`).
"""

from __future__ import annotations

import dataclasses
import shlex
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import tyro
from rich.console import Console

from dyngs.config import TrainConfig
from dyngs.configio import load_config, save_config
from dyngs.datamanagers.datamanager import DataManager, load_scene
from dyngs.datamanagers.scene_info import SCENE_FILE, SceneInfo
from dyngs.engine import schedules
from dyngs.engine.checkpoint import load_checkpoint, upgrade_checkpoint
from dyngs.engine.distributed import SINGLE, ProcessGroup, check_batch
from dyngs.engine.trainer import CHECKPOINT_NAME, StepHook, Trainer, resolve_device
from dyngs.engine.writer import NullWriter, TensorBoardWriter, Writer
from dyngs.errors import ConfigError, DatasetError
from dyngs.io import write_json
from dyngs.methods import method_presets
from dyngs.model import DynamicGaussians
from dyngs.renderers import RENDERERS, renderer_name
from dyngs.renderers.base import Renderer

# ---------------------------------------------------------------- training into a folder


def expand_argument_files(args: Sequence[str]) -> list[str]:
    """Replace each `@FILE` argument by the flags in FILE (one or more per line, `#`
    starts a comment)."""
    out: list[str] = []
    for arg in args:
        if arg.startswith("@") and len(arg) > 1:
            path = Path(arg[1:])
            if not path.is_file():
                raise ConfigError(f"{path}: argument file does not exist")
            for line in path.read_text().splitlines():
                out += shlex.split(line, comments=True)
        else:
            out.append(arg)
    return out


def parse_train_args(args: Sequence[str], description: str | None = None) -> TrainConfig:
    """The `dyngs-train` command line: a preset subcommand and flags, in any order."""
    presets, descriptions = method_presets()
    return tyro.cli(
        tyro.extras.subcommand_type_from_defaults(presets, descriptions),
        args=expand_argument_files(args),
        prog="dyngs-train",
        description=description,
        config=(tyro.conf.CascadeSubcommandArgs,),
    )


def new_run_dir(config: TrainConfig) -> Path:
    """OUTPUT_DIR/RUN_NAME, created; refuses a folder that already holds a checkpoint."""
    dataset = "demo" if config.data == "demo" else Path(config.data).resolve().name
    name = config.run_name or f"{config.method}-{dataset}-{time.strftime('%Y%m%d-%H%M%S')}"
    run_dir = config.output_dir / name
    if (run_dir / CHECKPOINT_NAME).exists():
        raise ConfigError(
            f"{run_dir}: this run already has a checkpoint; continue it with "
            f"`dyngs-train --resume {run_dir}` or choose another --run-name"
        )
    run_dir.mkdir(parents=True, exist_ok=True)
    return run_dir


def join_group(config: TrainConfig) -> ProcessGroup:
    """The processes this run trains in (torchrun's, or this one alone), checked to be no
    more than a step's views."""
    processes = ProcessGroup.requested_size()
    check_batch(processes, config.batch_views)  # before waiting for peers
    if processes > 1 and config.eval_split == "train":
        raise ConfigError(
            "--eval-split train with several processes: each holds only its share of the "
            "training images; evaluate afterwards with dyngs-eval --split train"
        )
    return ProcessGroup.join(config.collective_timeout, config.device)


def run_training(
    config: TrainConfig,
    run_dir: Path,
    console: Console,
    resume: bool = False,
    hooks: Sequence[StepHook] = (),
    group: ProcessGroup = SINGLE,
) -> dict[str, Any]:
    """Train into `run_dir` (continuing its checkpoint with `resume`) and write
    metrics.json; returns the metrics. `hooks` are called after every step. Of several
    processes (`group`), rank 0 alone writes files and reports; the others return {}."""
    main = group.is_main
    writer: Writer = NullWriter()
    if config.tensorboard and main:
        writer = TensorBoardWriter(run_dir / "tensorboard")
    try:
        trainer = Trainer(config, run_dir, writer, console if main else Console(quiet=True),
                          hooks=hooks, group=group)  # fmt: skip
        if resume:
            trainer.load(run_dir / CHECKPOINT_NAME)
            if main:
                console.print(f"resuming {run_dir} at step {trainer.step}")
        elif main:
            save_config(run_dir / "config.json", trainer.config)  # with data-sized values
        if main and (resume or not (run_dir / SCENE_FILE).exists()):
            SceneInfo.of(trainer.scene).write(run_dir / SCENE_FILE)
        metrics = trainer.train()
        if main:
            write_json(run_dir / "metrics.json", metrics)
    finally:
        writer.close()
    return metrics


# ---------------------------------------------------------------- loading a folder


@dataclass(frozen=True)
class RunOverrides:
    """Changes to how a run folder is loaded (all optional)."""

    device: str | None = None
    """Device to load onto (`cpu`, `cuda`, …); default: the one the run was trained with."""
    renderer: str = "run"
    """Renderer to draw with: `run` (the one trained with) or a registered one
    (`cpu-reference`, `cuda-tile`, or one an installed package adds)."""
    data: str | None = None
    """Dataset folder, when it has moved since training (default: the run's `--data`).
    Only evaluation reads it."""

    def __post_init__(self) -> None:
        if self.renderer != "run" and self.renderer not in RENDERERS:
            known = ", ".join(["run", *RENDERERS.names()])
            raise ConfigError(f"--renderer must be one of {known}, got {self.renderer!r}")


@dataclass(frozen=True)
class LoadedRun:
    """A trained run, ready to render: the model at its checkpoint (with its own SH
    degree and deformation state), its renderer, and its scene's cameras."""

    run_dir: Path
    config: TrainConfig
    """The run's resolved config, with any `RunOverrides` applied."""
    model: DynamicGaussians
    renderer: Renderer
    scene: SceneInfo
    device: torch.device
    step: int
    """Training iterations done when the checkpoint was written."""
    train_seconds: float

    def data(self) -> DataManager:
        """The run's dataset, served on its device (evaluation needs the images)."""
        cfg = self.config
        try:
            scene = load_scene(cfg.data, cfg.dataset, seed=cfg.seed)
        except DatasetError as error:
            raise DatasetError(
                f"{error} (the dataset of {self.run_dir}; if it moved, give --data NEW_PATH)"
            ) from None
        generator = torch.Generator().manual_seed(cfg.seed)
        return DataManager(scene, cfg.dataset, self.device, generator)


def _read_config(run_dir: Path, overrides: RunOverrides, device: str | None) -> TrainConfig:
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
    return dataclasses.replace(config, **changes)


def load_run(
    run_dir: Path | str,
    device: str | torch.device | None = None,
    overrides: RunOverrides | None = None,
) -> LoadedRun:
    """Rebuild a run from its folder (config.json, scene.json, checkpoint.pt).

    `device` (or `overrides.device`) moves it to another device; a missing or broken
    folder is a one-line `ConfigError` naming the path. Folders written before
    scene.json existed read their cameras from the dataset.
    """
    run_dir = Path(run_dir)
    overrides = overrides or RunOverrides()
    if not run_dir.is_dir():
        raise ConfigError(f"{run_dir}: no such run folder")
    config = _read_config(run_dir, overrides, None if device is None else str(device))
    checkpoint = run_dir / CHECKPOINT_NAME
    if not checkpoint.is_file():
        raise ConfigError(f"{checkpoint}: no checkpoint (has this run saved one yet?)")
    renderer = config.renderer.build()
    target = resolve_device(config.device)
    if (run_dir / SCENE_FILE).is_file():
        scene = SceneInfo.read(run_dir / SCENE_FILE)
    else:  # written before scene.json: the dataset says where the cameras were
        scene = SceneInfo.of(load_scene(config.data, config.dataset, seed=config.seed))
    state = load_checkpoint(checkpoint, "cpu")
    step = int(state["step"])
    upgrade_checkpoint(state, scene.scene_box, schedules.deforming(config, step))
    try:
        model = DynamicGaussians.load(config.gaussians, config.field, config.head, state["model"])
    except (KeyError, RuntimeError, ValueError) as error:
        first_line = str(error).strip().splitlines()[0] if str(error).strip() else ""
        raise ConfigError(
            f"{checkpoint}: does not fit {run_dir / 'config.json'} "
            f"({type(error).__name__}: {first_line})"
        ) from None
    model.to(target).eval()
    seconds = float(state["counters"].get("train_seconds", 0.0))
    return LoadedRun(run_dir, config, model, renderer, scene, target, step, seconds)

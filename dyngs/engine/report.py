"""What a run reports while it trains: TensorBoard scalars and the progress line.

Letters: H×W image.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from dyngs.config import TrainConfig
from dyngs.datamanagers.datamanager import TrainBatch
from dyngs.engine.motion import model_bytes
from dyngs.engine.writer import Writer
from dyngs.metrics import psnr
from dyngs.model import DynamicGaussians
from dyngs.renderers import renderer_name
from dyngs.renderers.base import RenderOutput


@dataclass
class StepStats:
    """What one training step did."""

    loss: Tensor
    terms: dict[str, Tensor]
    """The weighted loss terms by name (`dyngs.engine.objective`), detached."""
    out: RenderOutput
    batch: TrainBatch
    applied: bool = True
    """False when the step was skipped for a non-finite loss or gradient."""


@dataclass
class Counters:
    """Running totals of a run, saved with its checkpoint."""

    train_seconds: float = 0.0
    deformation_seconds: float = 0.0
    """Time spent deforming the Gaussians in training steps."""
    skipped_steps: int = 0
    """Steps skipped for a non-finite loss or gradient."""
    bad_streak: int = 0
    """Consecutive skipped steps up to now."""

    def record(self, good: bool) -> int:
        """Count a step, skipped unless `good`; returns the streak of skipped ones."""
        self.bad_streak = 0 if good else self.bad_streak + 1
        self.skipped_steps += 0 if good else 1
        return self.bad_streak

    def state_dict(self) -> dict[str, float | int]:
        return dict(vars(self))

    def load_state_dict(self, state: dict[str, float | int]) -> None:
        for name, value in vars(Counters()).items():
            setattr(self, name, type(value)(state.get(name, value)))


def capacity(model: DynamicGaussians, counters: Counters) -> dict[str, float]:
    """What the model costs: dynamic share (none while it does not deform), stored size,
    time spent deforming."""
    return {
        "dynamic_fraction": model.dynamic_fraction() if model.deforming else 0.0,
        "model_bytes": model_bytes(model),
        "deformation_seconds": counters.deformation_seconds,
        "deformation_share": counters.deformation_seconds / max(counters.train_seconds, 1e-9),
    }


def log_step(
    writer: Writer,
    step: int,
    stats: StepStats,
    model: DynamicGaussians,
    optimizer: torch.optim.Optimizer,
    counters: Counters,
    extra: dict[str, float],
) -> str:
    """Write the step's scalars and return the progress line. `extra` holds further
    scalars by tag (rate, culled Gaussians, importance time)."""
    loss = float(stats.loss)
    quality = float(psnr(stats.out.rgb.detach(), stats.batch.image))
    n = len(model.canonical)
    costs = capacity(model, counters)
    scalars = {
        "train/loss": loss,
        **{f"train/loss/{name}": float(value) for name, value in stats.terms.items()},
        "train/psnr": quality,
        "train/num_gaussians": n,
        **{f"train/{key}": amount for key, amount in costs.items()},
        "train/skipped_steps": counters.skipped_steps,
        **extra,
        **{f"learning_rate/{g['name']}": g["lr"] for g in optimizer.param_groups},
    }
    for tag, value in scalars.items():
        writer.scalar(tag, value, step)
    culled = int(extra.get("train/nonfinite_gaussians_culled", 0))
    skipped = f"  skipped {counters.skipped_steps}" if counters.skipped_steps else ""
    skipped += f"  culled non-finite {culled}" if culled else ""
    rate = extra.get("train/iterations_per_second", 0.0)
    return (
        f"loss {loss:.4f}  psnr {quality:5.2f}  gaussians {n:,}  "
        f"dynamic {costs['dynamic_fraction']:.1%}  "
        f"{costs['model_bytes'] / 2**20:.1f} MiB  {rate:.1f} it/s{skipped}"
    )


def run_summary(
    model: DynamicGaussians,
    counters: Counters,
    config: TrainConfig,
    step: int,
    device: torch.device,
    importance_seconds: float,
    filter_seconds: float,
) -> dict[str, object]:
    """What metrics.json says of a finished run besides its image metrics."""
    return {
        "num_gaussians": len(model.canonical),
        **capacity(model, counters),
        "static_scene": config.motion.separate and not model.any_dynamic(),
        "train_seconds": counters.train_seconds,
        "importance_seconds": importance_seconds,
        "filter_seconds": filter_seconds,
        "iterations": step,
        "skipped_steps": counters.skipped_steps,
        "renderer": renderer_name(config.renderer),
        "device": str(device),
    }


def write_metrics(writer: Writer, split: str, metrics: dict[str, object], step: int) -> None:
    """The evaluated split's PSNR, SSIM and LPIPS to TensorBoard."""
    for key in ("psnr", "ssim", "lpips"):
        value = metrics.get(key)
        if isinstance(value, float | int):
            writer.scalar(f"{split}/{key}", float(value), step)
    writer.flush()

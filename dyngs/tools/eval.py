"""`dyngs-eval`: score a trained run on a split, e.g. `dyngs-eval --load-dir outputs/RUN`.

Renders every view of the split, writes RUN/eval_<split>.json (mean and per-frame PSNR,
SSIM and LPIPS, render time per frame as mean, median and 95th percentile after a few
untimed warm-up renders, peak memory) and saves a render | ground-truth PNG per view in
RUN/eval_<split>/. LPIPS is null, with one warning, when its weights are absent.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import torch
import tyro
from rich.console import Console
from rich.table import Table

from dyngs.engine.evaluate import evaluate
from dyngs.engine.motion import model_bytes
from dyngs.errors import ConfigError
from dyngs.io import write_json
from dyngs.renderers import renderer_name
from dyngs.runs import LoadedRun, RunOverrides, load_run
from dyngs.tools.common import run_tool

Split = Literal["test", "val", "train"]


@dataclass(frozen=True)
class EvalConfig:
    """Evaluate a trained run on one split."""

    load_dir: Path
    """Run folder written by dyngs-train (holds config.json and checkpoint.pt)."""
    split: Split = "test"
    """Split to render and score."""
    output: Path | None = None
    """JSON file to write (default: LOAD_DIR/eval_<split>.json)."""
    save_images: bool = True
    """Save a render | ground-truth PNG of every view."""
    image_dir: Path | None = None
    """Folder for those images (default: LOAD_DIR/eval_<split>/)."""
    warmup: int = 3
    """Untimed renders before the timed ones (leaves one-off start-up costs out)."""
    run: Annotated[RunOverrides, tyro.conf.OmitArgPrefixes] = field(default_factory=RunOverrides)

    def __post_init__(self) -> None:
        if self.warmup < 0:
            raise ConfigError(f"--warmup must be ≥ 0, got {self.warmup}")


def evaluate_run(
    run: LoadedRun,
    split: str,
    image_dir: Path | None,
    warmup: int = 3,
    console: Console | None = None,
) -> dict[str, Any]:
    """`dyngs.engine.evaluate.evaluate` on a loaded run, plus what describes the run."""
    metrics = evaluate(
        run.model,
        run.renderer,
        run.data(),
        split,
        image_dir=image_dir,
        device=run.device,
        console=console,
        warmup=warmup,
    )
    return metrics | {
        "run_dir": str(run.run_dir),
        "method": run.config.method,
        "num_gaussians": len(run.model.canonical),
        "dynamic_fraction": run.model.dynamic_fraction() if run.model.deforming else 0.0,
        "model_bytes": model_bytes(run.model),
        "train_seconds": run.train_seconds,
        "iterations": run.step,
        "sh_degree": run.model.active_sh_degree,
        "deform": run.model.deforming,
        "renderer": renderer_name(run.config.renderer),
        "device": str(run.device),
        "cpu_threads": torch.get_num_threads(),  # render_ms depends on it on CPU
    }


def _cell(value: object, digits: int = 4) -> str:
    if value is None:
        return "null"
    return f"{value:.{digits}g}" if isinstance(value, float) else str(value)


def eval_table(metrics: dict[str, Any]) -> Table:
    table = Table(title=f"{metrics['split']} split, {metrics['num_frames']} views")
    columns = {
        "PSNR (dB)": metrics["psnr"],
        "SSIM": metrics["ssim"],
        "LPIPS": metrics["lpips"],
        "render ms (median)": metrics["render_ms_median"],
        "render ms (p95)": metrics["render_ms_p95"],
        "peak MiB": metrics["peak_memory_mb"],
        "Gaussians": metrics["num_gaussians"],
        "dynamic": metrics["dynamic_fraction"],
        "model MiB": metrics["model_bytes"] / 2**20,
        "deformation ms": metrics["deformation_ms"],
    }
    for name in columns:
        table.add_column(name, justify="right")
    table.add_row(*(_cell(v) for v in columns.values()))
    return table


def run_eval(config: EvalConfig, console: Console | None = None) -> dict[str, Any]:
    """Evaluate `config.load_dir` on its split; returns what was written to the JSON."""
    console = console or Console()
    run = load_run(config.load_dir, overrides=config.run)
    image_dir = None
    if config.save_images:
        image_dir = config.image_dir or run.run_dir / f"eval_{config.split}"
    metrics = evaluate_run(run, config.split, image_dir, config.warmup, console)
    output = config.output or run.run_dir / f"eval_{config.split}.json"
    write_json(output, metrics)
    console.print(eval_table(metrics))
    console.print(f"wrote {output}" + (f" and images in {image_dir}" if image_dir else ""))
    return metrics


def main(argv: Sequence[str] | None = None) -> None:
    def body(console: Console) -> None:
        config = tyro.cli(EvalConfig, args=argv, prog="dyngs-eval", description=__doc__)
        run_eval(config, console)

    run_tool(body)


if __name__ == "__main__":
    main()

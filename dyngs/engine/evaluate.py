"""Render a split, score it (PSNR, SSIM, LPIPS), save the images, time the renders.

The returned dict is what `metrics.json` (end of training) and `eval_<split>.json`
(`dyngs-eval`) hold. It never contains NaN or ±inf, so it is valid JSON: a metric that is
not finite (PSNR of a render identical to its ground truth) or cannot be computed (LPIPS
without its weights, or on images smaller than AlexNet accepts) is None (null).
"""

from __future__ import annotations

import math
import resource
import statistics
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from rich.console import Console
from rich.progress import Progress
from torch import Tensor

from dyngs.datamanagers.datamanager import DataManager, TrainBatch
from dyngs.engine.writer import to_uint8
from dyngs.metrics import LPIPS, load_lpips, psnr, ssim
from dyngs.model import DynamicGaussians
from dyngs.renderers.base import ABSENT_BELOW, Renderer


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def finite_or_none(value: float | None) -> float | None:
    """`value` when it is a finite number, else None (JSON has no inf or NaN)."""
    return value if value is not None and math.isfinite(value) else None


def peak_memory_mb(device: torch.device) -> tuple[float, str]:
    """Peak memory in MiB and what was measured: the CUDA caching allocator's peak since
    the last `torch.cuda.reset_peak_memory_stats` on a GPU, else the peak resident set of
    the whole process so far (it cannot be reset, so it includes any earlier work)."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20, "cuda_max_allocated"
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    per_unit = 1 if sys.platform == "darwin" else 1024  # bytes on macOS, KiB on Linux
    return peak * per_unit / 2**20, "process_max_rss"


@torch.no_grad()
def evaluate(
    model: DynamicGaussians,
    renderer: Renderer,
    data: DataManager,
    split: str,
    image_dir: Path | None,
    device: torch.device,
    console: Console | None = None,
    warmup: int = 1,
) -> dict[str, Any]:
    """Mean and per-frame metrics of `split`; render | ground-truth pairs go to `image_dir`.

    Timing is a pass of its own, before scoring (`time_renders`): scoring a frame between
    timed renders slowed the next render on CPU (LPIPS evicts the caches and reshapes the
    heap). `render_ms` is the mean time of deforming and drawing one frame, with its
    median and 95th percentile alongside; `deformation_ms` is the part spent deforming.
    """
    background = data.scene.background.to(device, torch.float32)
    if image_dir is not None:
        image_dir.mkdir(parents=True, exist_ok=True)
    views = list(data.views(split))
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    timings = time_renders(model, renderer, views, background, device, warmup)
    scorer = _Scorer(load_lpips(device), split)
    frames: list[dict[str, Any]] = []
    with Progress(console=console or Console(), transient=True) as progress:
        task = progress.add_task(f"evaluate {split}", total=len(views))
        for i, (view, (render_ms, deformation_ms)) in enumerate(zip(views, timings, strict=True)):
            drawn = model.at(view.time, absent_below=ABSENT_BELOW)
            rgb = model.camera_colour(renderer(drawn, view.camera, background).rgb, view.camera)
            rgb = rgb.clamp(0, 1)
            frame = {"index": i, "time": view.time, **scorer(i, rgb, view.image)}
            frames.append(frame | {"render_ms": render_ms, "deformation_ms": deformation_ms})
            if image_dir is not None:
                pair = torch.cat((rgb, view.image), dim=1)  # render | ground truth
                cv2.imwrite(
                    str(image_dir / f"{i:04d}.png"), cv2.cvtColor(to_uint8(pair), cv2.COLOR_RGB2BGR)
                )
            progress.advance(task)
    return summarize(split, frames, warmup, device)


def time_renders(
    model: DynamicGaussians,
    renderer: Renderer,
    views: list[TrainBatch],
    background: Tensor,
    device: torch.device,
    warmup: int,
) -> list[tuple[float, float]]:
    """(whole frame, deformation) milliseconds of every view, drawn back to back after
    `warmup` untimed renders of the first (leaving out one-off costs such as allocator
    growth and CUDA kernel loading)."""
    for _ in range(warmup if views else 0):
        renderer(model.at(views[0].time, absent_below=ABSENT_BELOW), views[0].camera, background)
    timings: list[tuple[float, float]] = []
    for view in views:
        _sync(device)
        started = time.perf_counter()
        gaussians = model.at(view.time, absent_below=ABSENT_BELOW)
        _sync(device)
        deformed = time.perf_counter()
        renderer(gaussians, view.camera, background)
        _sync(device)
        timings.append((1000 * (time.perf_counter() - started), 1000 * (deformed - started)))
    return timings


class _Scorer:
    """PSNR, SSIM and LPIPS of one frame; LPIPS is None without its weights, and for
    images below its minimum size (said once per split)."""

    def __init__(self, lpips: LPIPS | None, split: str) -> None:
        self.lpips, self.split, self.warned = lpips, split, False

    def __call__(self, index: int, rgb: Tensor, image: Tensor) -> dict[str, float | None]:
        perceptual: float | None = None
        if self.lpips is not None:
            if min(rgb.shape[0], rgb.shape[1]) >= LPIPS.MIN_SIZE:
                perceptual = float(self.lpips(rgb, image))
            elif not self.warned:
                self.warned = True
                warnings.warn(
                    f"LPIPS needs images of at least {LPIPS.MIN_SIZE}×{LPIPS.MIN_SIZE} px, "
                    f"{self.split} view {index} is {rgb.shape[0]}×{rgb.shape[1]}; "
                    "its LPIPS is null",
                    stacklevel=3,
                )
        return {
            "psnr": finite_or_none(float(psnr(rgb, image))),
            "ssim": float(ssim(rgb, image)),
            "lpips": perceptual,
        }


def summarize(
    split: str, frames: list[dict[str, Any]], warmup: int, device: torch.device
) -> dict[str, Any]:
    """The means over the frames, render-time percentiles and peak memory."""
    memory, memory_source = peak_memory_mb(device)

    def mean(key: str) -> float | None:
        # A frame whose PSNR was infinite makes the mean infinite too, hence None.
        if key == "psnr" and any(f["psnr"] is None for f in frames):
            return None
        values = [f[key] for f in frames if f[key] is not None]
        return finite_or_none(statistics.fmean(values)) if values else None

    times = [f["render_ms"] for f in frames]
    return {
        "split": split,
        "num_frames": len(frames),
        "psnr": mean("psnr"),
        "ssim": mean("ssim"),
        "lpips": mean("lpips"),
        "render_ms": mean("render_ms"),
        "deformation_ms": mean("deformation_ms"),
        "render_ms_median": statistics.median(times) if times else None,
        "render_ms_p95": float(np.percentile(times, 95)) if times else None,
        "warmup_renders": warmup,
        "peak_memory_mb": memory,
        "peak_memory_source": memory_source,
        "frames": frames,
    }

"""Render a split, score it (PSNR, SSIM, LPIPS), save the images, time the renders."""

from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import Any

import cv2
import torch
from rich.console import Console
from rich.progress import Progress

from dyngs.datamanagers.datamanager import DataManager
from dyngs.engine.writer import to_uint8
from dyngs.metrics import load_lpips, psnr, ssim
from dyngs.model import DynamicGaussians
from dyngs.renderers.base import Renderer


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@torch.no_grad()
def evaluate(
    model: DynamicGaussians,
    renderer: Renderer,
    data: DataManager,
    split: str,
    sh_degree: int,
    deform: bool,
    image_dir: Path | None,
    device: torch.device,
    console: Console | None = None,
) -> dict[str, Any]:
    """Mean and per-frame metrics of `split`; renders are written to `image_dir`."""
    lpips = load_lpips(device)
    background = data.scene.background.to(device, torch.float32)
    frames: list[dict[str, Any]] = []
    if image_dir is not None:
        image_dir.mkdir(parents=True, exist_ok=True)
    views = list(data.views(split))
    with Progress(console=console or Console(), transient=True) as progress:
        task = progress.add_task(f"evaluate {split}", total=len(views))
        for i, view in enumerate(views):
            _sync(device)
            started = time.perf_counter()
            gaussians = model.at(view.time, sh_degree, deform=deform)
            out = renderer(gaussians, view.camera, background)
            _sync(device)
            render_ms = 1000 * (time.perf_counter() - started)
            rgb = out.rgb.clamp(0, 1)
            frames.append(
                {
                    "index": i,
                    "time": view.time,
                    "psnr": float(psnr(rgb, view.image)),
                    "ssim": float(ssim(rgb, view.image)),
                    "lpips": None if lpips is None else float(lpips(rgb, view.image)),
                    "render_ms": render_ms,
                }
            )
            if image_dir is not None:
                pair = torch.cat((rgb, view.image), dim=1)  # render | ground truth
                cv2.imwrite(
                    str(image_dir / f"{i:04d}.png"), cv2.cvtColor(to_uint8(pair), cv2.COLOR_RGB2BGR)
                )
            progress.advance(task)

    def mean(key: str) -> float | None:
        values = [f[key] for f in frames if f[key] is not None]
        return statistics.fmean(values) if values else None

    return {
        "split": split,
        "psnr": mean("psnr"),
        "ssim": mean("ssim"),
        "lpips": mean("lpips"),
        "render_ms": mean("render_ms"),
        "frames": frames,
    }

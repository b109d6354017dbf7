"""One frame of the viewer: the model at a time, drawn by a renderer, as 8-bit RGB.

This is the viewer's whole render path; the server calls it on its render thread and
benchmarks/bench_viewer.py times it. What the page's toggles change is `Look`.

Letters: N Gaussians, H×W frame.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from jaxtyping import Float, UInt8
from torch import Tensor

from dyngs.engine.motion import model_bytes
from dyngs.engine.writer import to_uint8
from dyngs.model import DynamicGaussians
from dyngs.renderers import (
    CpuReferenceConfig,
    CpuTileConfig,
    RendererSpec,
    cpu_tile_available,
    default_renderer,
)
from dyngs.renderers.base import ABSENT_BELOW, Renderer
from dyngs.types import Camera, Gaussians

STATIC_COLOR = (0.30, 0.55, 0.95)
"""Colour of static Gaussians when motion is coloured (blue)."""
DYNAMIC_COLOR = (1.00, 0.45, 0.10)
"""Colour of dynamic (deformed) Gaussians when motion is coloured (orange)."""
DEPTH_PERCENTILES = (2.0, 98.0)
"""Depth is shown from the near to the far end of these percentiles of the drawn pixels,
so that a few stray Gaussians do not flatten the colour ramp."""


def fastest_renderer(device: torch.device | str) -> RendererSpec:
    """The fastest renderer for a model on `device`: cuda-tile on a GPU where gsplat is
    installed, else cpu-tile (compiled), else cpu-reference."""
    if torch.device(device).type == "cuda":
        return default_renderer()
    return CpuTileConfig() if cpu_tile_available() else CpuReferenceConfig()


@dataclass(frozen=True)
class Look:
    """What the page asks to see, besides camera and time."""

    deform: bool = True
    """Deformation on; off draws the canonical Gaussians."""
    motion_colors: bool = False
    """Colour static and dynamic Gaussians instead of their own colours."""
    depth: bool = False
    """Show expected depth (a colour ramp, near is warm) instead of colour."""


def motion_colored(gaussians: Gaussians, dynamic: Float[Tensor, " N"]) -> Gaussians:
    """The same Gaussians painted STATIC_COLOR or DYNAMIC_COLOR by the `dynamic` flags."""
    static = torch.tensor(STATIC_COLOR, dtype=gaussians.means.dtype, device=dynamic.device)
    moving = torch.tensor(DYNAMIC_COLOR, dtype=gaussians.means.dtype, device=dynamic.device)
    colors = torch.where(dynamic[:, None].bool(), moving, static)
    return dataclasses.replace(gaussians, colors=colors, sh_degree=None)


def depth_image(
    depth: Float[Tensor, "H W 1"], alpha: Float[Tensor, "H W 1"]
) -> UInt8[np.ndarray, "H W 3"]:
    """Expected depth as a colour ramp (OpenCV's turbo, near red, far blue) over the drawn
    pixels (alpha ≥ ½); black where nothing is drawn."""
    d = depth[..., 0].detach().float().cpu().numpy()
    drawn = alpha[..., 0].detach().float().cpu().numpy() >= 0.5
    if not drawn.any():
        return np.zeros((*d.shape, 3), dtype=np.uint8)
    near, far = np.percentile(d[drawn], DEPTH_PERCENTILES)
    scaled = 1.0 - np.clip((d - near) / max(far - near, 1e-9), 0.0, 1.0)
    ramp = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    rgb = cv2.cvtColor(ramp, cv2.COLOR_BGR2RGB)
    rgb[~drawn] = 0
    return rgb


@torch.no_grad()
def draw(
    model: DynamicGaussians,
    renderer: Renderer,
    camera: Camera,
    t: float,
    background: Float[Tensor, " 3"],
    look: Look = Look(),
) -> UInt8[np.ndarray, "H W 3"]:
    """The frame the viewer shows: the model at time t seen by `camera`, as `look` asks."""
    gaussians = model.at(t, deform=model.deforming and look.deform, absent_below=ABSENT_BELOW)
    if look.motion_colors:
        gaussians = motion_colored(gaussians, model.dynamic)
    device = gaussians.means.device
    out = renderer(gaussians, camera.to(device), background.to(device, torch.float32))
    if look.depth:
        return depth_image(out.depth, out.alpha)
    return to_uint8(out.rgb)


def model_summary(model: DynamicGaussians) -> str:
    """One line for the page: Gaussian count, dynamic share and stored size."""
    count = len(model.canonical)
    dynamic = 100.0 * model.dynamic_fraction()
    return f"{count:,} Gaussians ({dynamic:.0f} % dynamic), {model_bytes(model) / 2**20:.1f} MiB"

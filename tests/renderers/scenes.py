"""Random scenes and cameras for renderer tests: a deliberately uneven mix of tiny and
large, round and needle-like, faint and opaque Gaussians, some behind the camera or off
screen, seen by cameras with fx ≠ fy and an off-centre principal point."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from dyngs.types import Camera, Gaussians


def look_at(eye: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """World-to-camera 4×4 (OpenCV: x right, y down, z forward) for a camera at `eye`."""
    forward = (target - eye) / (target - eye).norm()
    right = torch.linalg.cross(forward, up)
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    rot = torch.stack((right, down, forward))
    w2c = torch.eye(4, dtype=eye.dtype)
    w2c[:3, :3] = rot
    w2c[:3, 3] = -rot @ eye
    return w2c


def random_camera(
    gen: torch.Generator, width: int, height: int, dtype: torch.dtype = torch.float64
) -> Camera:
    direction = torch.randn(3, generator=gen, dtype=torch.float64)
    eye = 4.0 * direction / direction.norm()
    up = torch.randn(3, generator=gen, dtype=torch.float64)
    w2c = look_at(eye, torch.zeros(3, dtype=torch.float64), up).to(dtype)
    fov = math.radians(40 + 40 * float(torch.rand(1, generator=gen)))
    fx = 0.5 * width / math.tan(0.5 * fov)
    fy = fx * (0.8 + 0.4 * float(torch.rand(1, generator=gen)))
    cx = width * (0.4 + 0.2 * float(torch.rand(1, generator=gen)))
    cy = height * (0.4 + 0.2 * float(torch.rand(1, generator=gen)))
    return Camera(fx, fy, cx, cy, w2c, width, height)


def random_gaussians(
    gen: torch.Generator,
    n: int,
    dtype: torch.dtype = torch.float64,
    sh_degree: int | None = None,
    spread: float = 1.5,
) -> Gaussians:
    def rand(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=gen, dtype=torch.float64)

    means = (rand(n, 3) * 2 - 1) * spread
    # Log-uniform sizes from specks to blobs, each axis stretched independently (up to
    # about 30:1 anisotropy).
    scales = torch.exp(math.log(0.004) + (math.log(0.6) - math.log(0.004)) * rand(n, 1))
    scales = scales * torch.exp(1.7 * (rand(n, 3) * 2 - 1))
    quats = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    opacities = rand(n) ** 0.5
    opacities[: n // 20] = 0.5 / 255  # a few too faint to ever draw
    if sh_degree is None:
        colors = rand(n, 3)
    else:
        colors = 0.4 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=gen, dtype=torch.float64)
    return Gaussians(
        means.to(dtype), quats.to(dtype), scales.to(dtype), opacities.to(dtype),
        colors.to(dtype), sh_degree,
    )  # fmt: skip


def random_scene(
    seed: int,
    n: int,
    width: int,
    height: int,
    dtype: torch.dtype = torch.float64,
    sh_degree: int | None = None,
) -> tuple[Gaussians, Camera, Tensor]:
    gen = torch.Generator().manual_seed(seed)
    camera = random_camera(gen, width, height, dtype)
    gaussians = random_gaussians(gen, n, dtype, sh_degree)
    background = torch.rand(3, generator=gen, dtype=torch.float64).to(dtype)
    return gaussians, camera, background

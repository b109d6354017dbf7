"""`dyngs.rasterize`: raw tensors in, any registered renderer, the same image as that
renderer called on the same `Gaussians` and `Camera`."""

from __future__ import annotations

import pytest
import torch

import dyngs
from dyngs.errors import RendererUnavailable
from dyngs.renderers import CpuReferenceConfig
from dyngs.types import Camera, Gaussians
from tests.renderers.scenes import random_camera, random_gaussians


def _intrinsics(camera: Camera) -> torch.Tensor:
    return torch.tensor(
        [[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]],
        dtype=torch.float64,
    )


@pytest.mark.parametrize("sh_degree", [None, 2])
def test_rasterize_draws_what_the_renderer_draws(sh_degree: int | None) -> None:
    gen = torch.Generator().manual_seed(7)
    g = random_gaussians(gen, 200, sh_degree=sh_degree)
    camera = random_camera(gen, 45, 31)
    background = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)
    direct = CpuReferenceConfig().build()(g, camera, background)
    flat = dyngs.rasterize(
        g.means, g.quats, g.scales, g.opacities, g.colors, camera.world_to_camera,
        _intrinsics(camera), camera.width, camera.height, sh_degree=sh_degree,
        background=background, renderer="cpu-reference", contribution=True,
    )  # fmt: skip
    for name in ("rgb", "alpha", "depth", "radii", "visible"):
        assert torch.equal(getattr(flat, name), getattr(direct, name)), name
    assert flat.contribution is not None and direct.contribution is None
    assert float(flat.contribution.sum()) == pytest.approx(float(flat.alpha.sum()), rel=1e-9)


def test_contribution_needs_a_renderer_that_measures_it() -> None:
    class Plain:
        def __call__(self, gaussians: Gaussians, camera: Camera, background: torch.Tensor):  # type: ignore[no-untyped-def]
            return CpuReferenceConfig().build()(gaussians, camera, background)

    gen = torch.Generator().manual_seed(1)
    g = random_gaussians(gen, 20)
    camera = random_camera(gen, 16, 16)
    args = (g.means, g.quats, g.scales, g.opacities, g.colors, camera.world_to_camera,
            _intrinsics(camera), 16, 16)  # fmt: skip
    assert dyngs.rasterize(*args, renderer=Plain()).contribution is None
    with pytest.raises(RendererUnavailable, match="cannot measure contribution"):
        dyngs.rasterize(*args, renderer=Plain(), contribution=True)
    with pytest.raises(Exception, match="unknown renderer 'no-such'"):
        dyngs.rasterize(*args, renderer="no-such")

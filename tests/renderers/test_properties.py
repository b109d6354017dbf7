"""Property-based test of every available renderer (issue 5, docs/NUMERICS.md).

Hypothesis draws random valid scenes and cameras: image sizes from 1×1 up, float32 or
float64, fields of view from 0.5° to 170°, fx ≠ fy, off-centre principal points, cameras up
to 1e4 units from the origin, Gaussians in front of, around and behind the camera, with
scales from 1e-8 to 1e4 per axis (so anisotropy up to 1e12), quaternions of norm 1e-20
to 1e20 or zero, opacities from 0 to 1 inclusive, and RGB or SH colours in [0, 1]. For each
scene: rgb and alpha lie in [0, 1], depth is ≥ 0, all three are finite, nothing is counted
as non-finite, and one backward pass gives finite gradients for every parameter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from torch import Tensor

from dyngs.renderers.base import Renderer
from dyngs.renderers.cpu_reference import CpuReferenceConfig
from dyngs.renderers.cpu_tile import CpuTileConfig
from dyngs.renderers.cuda_tile import CudaTileConfig, cuda_tile_available
from dyngs.types import Camera, Gaussians
from tests.renderers.scenes import look_at

MAX_EXAMPLES = 60
"""Scenes drawn per renderer (read by benchmarks/count_hard_cases.py)."""

RENDERERS = ["cpu-reference", "cpu-tile"] + (["cuda-tile"] if cuda_tile_available() else [])

# The SH basis functions of degree ≤ 3 are at most 1 in magnitude on the unit sphere, so
# coefficients whose absolute sum is ≤ 0.25 move a colour by at most 0.25.
_SH_REST_BUDGET = 0.25
_SH_C0 = 0.5 / math.sqrt(math.pi)


@dataclass(frozen=True)
class SceneSpec:
    """What hypothesis draws; tensors are then generated from `seed`."""

    seed: int
    n: int
    width: int
    height: int
    float64: bool
    fov_degrees: float
    aspect: float
    distance: float
    offset: float
    spread: float
    log_scale_low: float
    log_scale_high: float
    sh_degree: int | None


scene_specs = st.builds(
    SceneSpec,
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(0, 48),
    width=st.integers(1, 96),
    height=st.integers(1, 72),
    float64=st.booleans(),
    fov_degrees=st.one_of(st.sampled_from([0.5, 170.0]), st.floats(0.5, 170.0)),
    aspect=st.floats(0.7, 1.4),
    distance=st.floats(0.05, 20.0),
    offset=st.sampled_from([0.0, 1.0, 1e4]),
    spread=st.floats(0.01, 3.0),
    log_scale_low=st.floats(-8.0, 4.0),
    log_scale_high=st.floats(-8.0, 4.0),
    sh_degree=st.sampled_from([None, 0, 1, 2, 3]),
)


def build_scene(spec: SceneSpec) -> tuple[Gaussians, Camera, Tensor]:
    """A scene and camera in float64 (cast to the drawn dtype by the caller)."""
    gen = torch.Generator().manual_seed(spec.seed)

    def rand(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=gen, dtype=torch.float64)

    def randn(*shape: int) -> Tensor:
        return torch.randn(*shape, generator=gen, dtype=torch.float64)

    # The camera looks at a target `distance` away from a random direction; everything is
    # shifted by `offset` along a random direction.
    shift = spec.offset * randn(3) / randn(3).norm().clamp_min(1e-3)
    direction = randn(3)
    direction = direction / direction.norm().clamp_min(1e-12)
    eye = shift + spec.distance * direction
    up = randn(3)
    if float(torch.linalg.cross(direction, up).norm()) < 1e-3:
        up = torch.tensor([0.3, -1.0, 0.1], dtype=torch.float64)
    w2c = look_at(eye, shift, up)
    fx = 0.5 * spec.width / math.tan(math.radians(spec.fov_degrees) / 2)
    cx = spec.width * float(0.2 + 0.6 * rand(1))
    cy = spec.height * float(0.2 + 0.6 * rand(1))
    camera = Camera(fx, fx * spec.aspect, cx, cy, w2c, spec.width, spec.height)

    # Gaussians around the target, as far out as spread × distance: some behind the camera.
    n = spec.n
    means = shift + (2 * rand(n, 3) - 1) * spec.spread * spec.distance
    low, high = sorted((spec.log_scale_low, spec.log_scale_high))
    scales = 10 ** (low + (high - low) * rand(n, 3))
    quats = randn(n, 4) * 10 ** (40 * rand(n, 1) - 20)
    quats[rand(n) < 0.1] = 0.0
    opacities = rand(n)
    opacities[rand(n) < 0.1] = 1.0
    opacities[rand(n) < 0.05] = 0.0
    if spec.sh_degree is None:
        colors = rand(n, 3)
    else:
        k = (spec.sh_degree + 1) ** 2
        base = 0.25 + 0.5 * rand(n, 1, 3)  # colour from degree 0 alone, in [0.25, 0.75]
        rest = 2 * rand(n, k - 1, 3) - 1
        rest = rest / max(k - 1, 1) * _SH_REST_BUDGET
        colors = torch.cat(((base - 0.5) / _SH_C0, rest), dim=1)
    background = rand(3)
    gaussians = Gaussians(means, quats, scales, opacities, colors, spec.sh_degree)
    return gaussians, camera, background


@pytest.mark.parametrize("renderer", RENDERERS)
@settings(
    max_examples=MAX_EXAMPLES,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(spec=scene_specs)
def test_random_valid_scenes_render_in_range_with_finite_gradients(
    renderer: str, spec: SceneSpec
) -> None:
    gaussians, camera, background = build_scene(spec)
    draw: Renderer
    if renderer == "cuda-tile":
        device, dtype = "cuda", torch.float32
        draw = CudaTileConfig().build()
    else:
        device, dtype = "cpu", torch.float64 if spec.float64 else torch.float32
        draw = CpuTileConfig().build() if renderer == "cpu-tile" else CpuReferenceConfig().build()
    g = gaussians.to(device=device, dtype=dtype)
    names = ("means", "quats", "scales", "opacities", "colors")
    leaves = {k: getattr(g, k).detach().clone().requires_grad_(True) for k in names}
    out = draw(
        replace(g, **leaves),
        camera.to(device=device, dtype=dtype),
        background.to(device=device, dtype=dtype),
    )
    rgb, alpha, depth = out.rgb.detach(), out.alpha.detach(), out.depth.detach()
    for name, value in (("rgb", rgb), ("alpha", alpha), ("depth", depth)):
        assert bool(torch.isfinite(value).all()), f"{name} is not finite"
    assert float(rgb.min()) >= 0 and float(rgb.max()) <= 1
    assert float(alpha.min()) >= 0 and float(alpha.max()) <= 1
    assert float(depth.min()) >= 0
    assert int(out.num_nonfinite) == 0

    weights = torch.tensor([0.3, -0.5, 0.7], device=device, dtype=dtype)
    (((out.rgb * weights).sum() + out.alpha.sum()) + 0.1 * out.depth.sum()).backward()
    for name, leaf in leaves.items():
        assert leaf.grad is None or bool(torch.isfinite(leaf.grad).all()), name

"""Hard cases for the fields and the model's time input (issue 5, docs/NUMERICS.md).

Times exactly 0 and 1, times outside [0, 1], points outside the scene box, and very large
and very small HexPlane grids. Every case checks finite outputs and finite gradients;
where a brute-force answer exists (the HexPlane product of bilinear samples, the MLP's
positional encoding) the output equals it.

Letters: N points, F features.
"""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from dyngs.fields import (
    DeformationHeadConfig,
    HexPlaneConfig,
    HexPlaneField,
    MLPField,
    MLPFieldConfig,
)
from dyngs.fields.hexplane import PLANE_AXES
from dyngs.model import CanonicalGaussians, DynamicGaussians, GaussianConfig
from dyngs.renderers.cpu_reference import CpuReferenceRenderer
from dyngs.types import SceneBox
from tests.renderers.scenes import random_camera

BOX = SceneBox((-1.0, -2.0, 0.5), (2.0, 1.0, 4.5))
DTYPES = [pytest.param(torch.float32, id="float32"), pytest.param(torch.float64, id="float64")]


def _tolerance(dtype: torch.dtype) -> float:
    return 1e-12 if dtype == torch.float64 else 1e-5


def _inside(n: int, seed: int, dtype: torch.dtype) -> Tensor:
    gen = torch.Generator().manual_seed(seed)
    lower = torch.tensor(BOX.lower, dtype=torch.float64)
    size = torch.tensor(BOX.size, dtype=torch.float64)
    return (lower + torch.rand(n, 3, generator=gen, dtype=torch.float64) * size).to(dtype)


def _hexplane(
    resolution: tuple[int, int, int, int] = (5, 6, 7, 4),
    multires: tuple[int, ...] = (1, 2),
    features: int = 3,
    dtype: torch.dtype = torch.float64,
) -> HexPlaneField:
    """A HexPlane whose time planes depart from 1, so that time matters."""
    config = HexPlaneConfig(resolution=resolution, multires=multires, features=features)
    field = config.build(BOX, generator=torch.Generator().manual_seed(1)).to(dtype)
    gen = torch.Generator().manual_seed(2)
    with torch.no_grad():
        for plane in field.planes().temporal:
            noise = torch.randn(plane.shape, generator=gen, dtype=torch.float64)
            plane.add_(0.3 * noise.to(dtype))
    return field


def _bilinear(plane: Tensor, u: float, v: float) -> Tensor:
    """Brute force: [F, H, W] sampled at u (along W) and v (along H) in [-1, 1], with -1
    and 1 on the centres of the edge texels (align_corners=True)."""
    h, w = plane.shape[-2:]
    x, y = (u + 1) / 2 * (w - 1), (v + 1) / 2 * (h - 1)
    x0, y0 = min(math.floor(x), max(w - 2, 0)), min(math.floor(y), max(h - 2, 0))
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0

    def texel(row: int, col: int) -> Tensor:
        return plane[:, row, col].double()

    return (
        texel(y0, x0) * (1 - fx) * (1 - fy)
        + texel(y0, x1) * fx * (1 - fy)
        + texel(y1, x0) * (1 - fx) * fy
        + texel(y1, x1) * fx * fy
    )


def _brute_force(field: HexPlaneField, xyz: Tensor, t: Tensor) -> Tensor:
    """Per point, per scale: the product of the six planes' bilinear samples at the
    box-normalised, clamped coordinates; scales concatenated. float64 throughout."""
    planes = field.planes()
    scales = len(field.config.multires)
    rows = []
    for point, time in zip(xyz.double().tolist(), t.double().expand(len(xyz), 1).tolist(),
                           strict=True):  # fmt: skip
        unit = [(point[i] - BOX.lower[i]) / BOX.size[i] * 2 - 1 for i in range(3)]
        coords = [min(max(c, -1.0), 1.0) for c in (*unit, 2 * time[0] - 1)]
        per_scale = []
        for s in range(scales):
            product = torch.ones(field.features, dtype=torch.float64)
            for p, (a, b) in enumerate(PLANE_AXES):
                plane = planes.spatial[3 * s + p] if p < 3 else planes.temporal[3 * s + p - 3]
                product = product * _bilinear(plane.detach(), coords[a], coords[b])
            per_scale.append(product)
        rows.append(torch.cat(per_scale))
    return torch.stack(rows)


def _assert_finite_gradients(module: torch.nn.Module, *inputs: Tensor) -> None:
    for name, p in module.named_parameters():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()), name
    for x in inputs:
        assert x.grad is not None and bool(torch.isfinite(x.grad).all())


# ---------------------------------------------------------------------------------------
# Time exactly at the ends of [0, 1]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("time", [0.0, 1.0])
def test_hexplane_at_time_exactly_0_and_1(dtype: torch.dtype, time: float) -> None:
    # t = 0 and 1 map to −1 and 1: the centres of the first and last time texels.
    field = _hexplane(dtype=dtype)
    xyz = _inside(40, 3, dtype).requires_grad_(True)
    t = torch.full((40, 1), time, dtype=dtype, requires_grad=True)
    out = field(xyz, t)
    assert bool(torch.isfinite(out).all())
    want = _brute_force(field, xyz.detach(), t.detach())
    assert float((out.detach().double() - want).abs().max()) <= _tolerance(dtype)
    out.square().sum().backward()
    _assert_finite_gradients(field, xyz, t)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("time", [0.0, 1.0])
def test_mlp_at_time_exactly_0_and_1(dtype: torch.dtype, time: float) -> None:
    config = MLPFieldConfig(position_frequencies=4, time_frequencies=6, depth=3, width=16)
    field = config.build(BOX, generator=torch.Generator().manual_seed(4)).to(dtype)
    xyz = _inside(20, 5, dtype).requires_grad_(True)
    t = torch.full((20, 1), time, dtype=dtype, requires_grad=True)
    # Brute force of the time encoding: [τ, sin(2ᵏπτ), cos(2ᵏπτ)] for τ = 2t − 1 = ±1.
    tau = 2 * time - 1
    bands = [2.0**k * math.pi * tau for k in range(6)]
    want = [tau, *(math.sin(b) for b in bands), *(math.cos(b) for b in bands)]
    encoded_time = field.encode(xyz, t)[:, -13:].detach()
    # The largest angle, 2⁵π, carries its rounding: 2⁵π·2⁻²⁴ ≈ 6e-6 in float32.
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert encoded_time[0].double().tolist() == pytest.approx(want, abs=tol)
    out = field(xyz, t)
    assert bool(torch.isfinite(out).all())
    out.square().sum().backward()
    _assert_finite_gradients(field, xyz, t)


# ---------------------------------------------------------------------------------------
# Time outside [0, 1]


def _model() -> DynamicGaussians:
    gen = torch.Generator().manual_seed(6)
    points = _inside(12, 7, torch.float32)
    canonical = CanonicalGaussians.from_points(points, None, GaussianConfig(sh_degree=1), gen)
    field = HexPlaneConfig(resolution=(4, 4, 4, 3), multires=(1,), features=4).build(BOX)
    head = DeformationHeadConfig(width=8).build(field.out_dim, BOX, generator=gen)
    return DynamicGaussians(canonical, field, head, BOX)


@pytest.mark.parametrize("time", [-1e-9, 1 + 1e-9, -0.5, 1.5, math.nan, math.inf, -math.inf])
def test_model_time_outside_0_1_is_a_clear_error(time: float) -> None:
    # Datasets give t ∈ [0, 1] (docs/DESIGN.md); the model refuses anything else by name.
    model = _model()
    with pytest.raises(ValueError, match=r"time must be in \[0, 1\]"):
        model.at(time, sh_degree=1)


@pytest.mark.parametrize("time", [0.0, 1.0])
def test_model_at_time_exactly_0_and_1(time: float) -> None:
    model = _model()
    g = model.at(time, sh_degree=1)
    loss = sum(t.square().sum() for t in (g.means, g.quats, g.scales, g.opacities, g.colors))
    assert isinstance(loss, Tensor) and bool(torch.isfinite(loss))
    loss.backward()
    for name, p in model.named_parameters():
        assert p.grad is None or bool(torch.isfinite(p.grad).all()), name


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("time", [-0.5, -1e30, 1.5, 1e30])
def test_hexplane_time_outside_0_1_is_clamped_to_the_nearest_end(
    dtype: torch.dtype, time: float
) -> None:
    # Documented in HexPlaneField: a time outside [0, 1] reads the nearest end of time,
    # exactly, and gets a zero gradient.
    field = _hexplane(dtype=dtype)
    xyz = _inside(30, 8, dtype)
    t = torch.full((30, 1), time, dtype=dtype, requires_grad=True)
    end = torch.full((30, 1), 0.0 if time < 0 else 1.0, dtype=dtype)
    out = field(xyz, t)
    assert torch.equal(out, field(xyz, end))
    out.sum().backward()
    assert t.grad is not None and bool((t.grad == 0).all())


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("time", [-3.0, 4.0, 1e3])
def test_mlp_time_outside_0_1_extrapolates_finitely(dtype: torch.dtype, time: float) -> None:
    # Documented in MLPField: no clamp, the encoding is defined for every finite time.
    config = MLPFieldConfig(depth=3, width=16)
    field = config.build(BOX, generator=torch.Generator().manual_seed(9)).to(dtype)
    xyz = _inside(10, 10, dtype).requires_grad_(True)
    t = torch.full((10, 1), time, dtype=dtype, requires_grad=True)
    out = field(xyz, t)
    assert bool(torch.isfinite(out).all())
    out.square().sum().backward()
    _assert_finite_gradients(field, xyz, t)


# ---------------------------------------------------------------------------------------
# Points outside the scene box


@pytest.mark.parametrize("dtype", DTYPES)
def test_hexplane_points_outside_the_box_read_the_nearest_box_point(dtype: torch.dtype) -> None:
    field = _hexplane(dtype=dtype)
    big = torch.finfo(dtype).max / 4  # the normalisation must not overflow either
    xyz = torch.tensor(
        [[-5.0, 0.0, 1.0], [0.5, 40.0, 2.0], [1.0, -1.0, -100.0], [1e6, -1e6, 1e6],
         [big, -big, big], [-big, 0.0, 3.0]],
        dtype=dtype, requires_grad=True,
    )  # fmt: skip
    t = torch.tensor([[0.0], [0.3], [0.5], [0.7], [1.0], [0.2]], dtype=dtype)
    out = field(xyz, t)
    assert bool(torch.isfinite(out).all())
    want = _brute_force(field, xyz.detach(), t)
    assert float((out.detach().double() - want).abs().max()) <= _tolerance(dtype)
    out.square().sum().backward()
    assert xyz.grad is not None and bool(torch.isfinite(xyz.grad).all())
    lower = torch.tensor(BOX.lower, dtype=dtype)
    upper = torch.tensor(BOX.upper, dtype=dtype)
    outside = (xyz.detach() < lower) | (xyz.detach() > upper)
    assert bool((xyz.grad[outside] == 0).all())  # clamped axes get no gradient


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("distance", [10.0, 1e3, 1e6])
def test_mlp_points_outside_the_box_are_finite(dtype: torch.dtype, distance: float) -> None:
    field = MLPFieldConfig(depth=3, width=16).build(BOX).to(dtype)
    direction = torch.tensor([[1.0, -0.5, 0.25], [-0.3, 0.9, -1.0]], dtype=dtype)
    xyz = (direction * distance).requires_grad_(True)
    t = torch.tensor([[0.25], [0.75]], dtype=dtype, requires_grad=True)
    out = field(xyz, t)
    assert bool(torch.isfinite(out).all())
    out.square().sum().backward()
    _assert_finite_gradients(field, xyz, t)


def _field(kind: str, dtype: torch.dtype) -> HexPlaneField | MLPField:
    if kind == "hexplane":
        return _hexplane(dtype=dtype)
    config = MLPFieldConfig(depth=3, width=16)
    return config.build(BOX, generator=torch.Generator().manual_seed(14)).to(dtype)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", ["hexplane", "mlp"])
def test_non_finite_point_reads_the_box_centre_with_zero_gradient(
    kind: str, dtype: torch.dtype
) -> None:
    # A NaN or ±Inf mean (culled and counted by the renderers) must not break the field:
    # a NaN reaching grid_sample's backward crashed the process, and NaN activations in the
    # MLP turned every weight gradient into NaN. The coordinate reads the box centre.
    field = _field(kind, dtype)
    centre = BOX.center
    xyz = torch.tensor(
        [[math.nan, 0.0, 1.0], [0.5, math.inf, 2.0], [1.0, -0.5, -math.inf], [0.2, 0.1, 3.0]],
        dtype=dtype, requires_grad=True,
    )  # fmt: skip
    t = torch.tensor([[0.1], [0.4], [0.6], [0.9]], dtype=dtype)
    out = field(xyz, t)
    assert bool(torch.isfinite(out).all())
    replaced = torch.where(torch.isfinite(xyz), xyz, torch.tensor(centre, dtype=dtype))
    assert torch.equal(out, field(replaced.detach(), t))
    out.square().sum().backward()
    assert xyz.grad is not None and bool(torch.isfinite(xyz.grad).all())
    assert bool((xyz.grad[~torch.isfinite(xyz.detach())] == 0).all())
    for name, p in field.named_parameters():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()), name


@pytest.mark.parametrize("kind", ["hexplane", "mlp"])
def test_nan_canonical_mean_is_culled_counted_and_leaves_every_gradient_finite(kind: str) -> None:
    # The whole road: a canonical mean gone NaN is deformed by the field, culled and counted
    # by the renderer, and the backward reaches every parameter with finite values.
    base = _model()
    field = _field(kind, torch.float32)
    head = DeformationHeadConfig(width=8, opacity=True, color=True).build(field.out_dim, BOX)
    model = DynamicGaussians(base.canonical, field, head, BOX)
    with torch.no_grad():
        model.canonical.means[3, 0] = math.nan
        for p in head.parameters():  # leave the zero start, so the deltas read the field
            p.add_(0.01)
    camera = random_camera(torch.Generator().manual_seed(15), 20, 16, torch.float32)
    out = CpuReferenceRenderer()(model.at(0.5, sh_degree=1), camera, torch.zeros(3))
    assert int(out.num_nonfinite) == 1 and not bool(out.visible[3])
    assert bool(torch.isfinite(out.rgb).all()) and float(out.alpha.detach().max()) > 0
    (out.rgb.sum() + out.depth.sum()).backward()
    for name, p in model.named_parameters():
        assert p.grad is None or bool(torch.isfinite(p.grad).all()), name
    means_grad = model.canonical.means.grad
    assert means_grad is not None and bool((means_grad[3] == 0).all())


# ---------------------------------------------------------------------------------------
# Grid sizes


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize(
    ("resolution", "multires"),
    [((1, 1, 1, 1), (1,)), ((2, 2, 2, 2), (1,)), ((1, 2, 1, 1), (1, 4)), ((2, 1, 3, 1), (1, 2))],
)
def test_hexplane_very_small_grids(
    dtype: torch.dtype, resolution: tuple[int, int, int, int], multires: tuple[int, ...]
) -> None:
    # One texel along an axis: every coordinate reads that texel, and the gradient along
    # the axis is zero.
    field = _hexplane(resolution, multires, features=2, dtype=dtype)
    xyz = torch.cat((_inside(10, 11, dtype), torch.tensor([[9.0, -9.0, 9.0]], dtype=dtype)))
    xyz.requires_grad_(True)
    t = torch.linspace(0, 1, 11, dtype=dtype)[:, None].requires_grad_(True)
    out = field(xyz, t)
    assert out.shape == (11, 2 * len(multires)) and bool(torch.isfinite(out).all())
    want = _brute_force(field, xyz.detach(), t.detach())
    assert float((out.detach().double() - want).abs().max()) <= _tolerance(dtype)
    out.square().sum().backward()
    _assert_finite_gradients(field, xyz, t)


@pytest.mark.parametrize("dtype", DTYPES)
def test_hexplane_very_large_grid(dtype: torch.dtype) -> None:
    # 2048² texels in the xy plane and 512 time cells: texel indices near 2047 leave float32
    # a relative spacing of 6e-8, about 1e-4 of a texel, so float32 is held to 1e-5
    # (features here are at most 0.5³ with slopes ≤ 0.4 per texel).
    field = _hexplane((2048, 2048, 2, 512), (1,), features=1, dtype=dtype)
    xyz = _inside(200, 12, dtype).requires_grad_(True)
    t = torch.rand(200, 1, generator=torch.Generator().manual_seed(13), dtype=torch.float64)
    t = t.to(dtype).requires_grad_(True)
    out = field(xyz, t)
    want = _brute_force(field, xyz.detach(), t.detach())
    assert float((out.detach().double() - want).abs().max()) <= _tolerance(dtype)
    out.square().sum().backward()
    _assert_finite_gradients(field, xyz, t)

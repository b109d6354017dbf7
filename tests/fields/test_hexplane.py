"""HexPlaneField: shapes, the static start, hand-computed bilinear samples, the box
normalisation, clamping, gradients (gradcheck) and extreme grid sizes."""

from __future__ import annotations

import itertools

import pytest
import torch
from torch import Tensor

from dyngs.errors import ConfigError
from dyngs.fields import HexPlaneConfig, HexPlaneField
from dyngs.fields.hexplane import PLANE_AXES
from dyngs.types import SceneBox

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
BOX = SceneBox((-1.0, -2.0, 0.5), (2.0, 1.0, 4.5))


def _points(n: int, box: SceneBox, generator: torch.Generator, dtype: torch.dtype) -> Tensor:
    lower = torch.tensor(box.lower, dtype=dtype)
    size = torch.tensor(box.size, dtype=dtype)
    return lower + torch.rand(n, 3, generator=generator, dtype=dtype) * size


def _perturb_time_planes(field: HexPlaneField, generator: torch.Generator) -> None:
    with torch.no_grad():
        for plane in field.planes().temporal:
            plane.add_(0.3 * torch.randn(plane.shape, generator=generator, dtype=plane.dtype))


def _bilinear(plane: Tensor, u: float, v: float) -> Tensor:
    """Reference: sample [F, H, W] at (u along W, v along H) in [-1, 1], corners on texels."""
    _, h, w = plane.shape
    px, py = (u + 1) / 2 * (w - 1), (v + 1) / 2 * (h - 1)
    x0, y0 = min(int(px), max(w - 2, 0)), min(int(py), max(h - 2, 0))
    fx, fy = px - x0, py - y0
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    return (
        plane[:, y0, x0] * (1 - fx) * (1 - fy)
        + plane[:, y0, x1] * fx * (1 - fy)
        + plane[:, y1, x0] * (1 - fx) * fy
        + plane[:, y1, x1] * fx * fy
    )


def _reference(field: HexPlaneField, xyz: Tensor, t: Tensor) -> Tensor:
    """Per-point product of the six planes' bilinear samples, scale after scale."""
    box = field.box
    planes = field.planes()
    scales = len(field.config.multires)
    rows = []
    for p, time in zip(xyz.tolist(), t[:, 0].tolist(), strict=True):
        unit = [min(max((p[i] - box.lower[i]) / box.size[i] * 2 - 1, -1.0), 1.0) for i in range(3)]
        coords = [*unit, min(max(2 * time - 1, -1.0), 1.0)]
        feats = []
        for s in range(scales):
            product = torch.ones(field.features, dtype=xyz.dtype)
            for k, (a, b) in enumerate(PLANE_AXES):
                plane = planes.spatial[3 * s + k] if k < 3 else planes.temporal[3 * s + k - 3]
                product = product * _bilinear(plane.detach(), coords[a], coords[b])
            feats.append(product)
        rows.append(torch.cat(feats))
    return torch.stack(rows)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [0, 1, 37])
def test_shapes_and_dtypes(dtype: torch.dtype, n: int) -> None:
    g = torch.Generator().manual_seed(0)
    field = HexPlaneConfig(resolution=(6, 5, 4, 3), multires=(1, 2), features=8).build(BOX)
    field = field.to(dtype)
    assert field.out_dim == 16
    xyz = _points(n, BOX, g, dtype).requires_grad_()
    t = torch.rand(n, 1, generator=g, dtype=dtype)
    out = field(xyz, t)
    assert out.shape == (n, 16) and out.dtype == dtype and out.is_contiguous()
    assert bool(torch.isfinite(out).all())
    out.square().sum().backward()
    assert xyz.grad is not None and xyz.grad.shape == (n, 3)


def test_time_broadcast_and_bad_shapes() -> None:
    field = HexPlaneConfig(resolution=(4, 4, 4, 3), features=4).build(BOX)
    _perturb_time_planes(field, torch.Generator().manual_seed(1))
    xyz = _points(5, BOX, torch.Generator().manual_seed(2), torch.float32)
    one = torch.tensor([[0.3]])
    assert torch.equal(field(xyz, one), field(xyz, one.expand(5, 1)))
    with pytest.raises(ValueError, match="t must be"):
        field(xyz, torch.zeros(5))
    with pytest.raises(ValueError, match="xyz must be"):
        field(xyz[:, :2], torch.zeros(5, 1))


def test_plane_layout_and_views() -> None:
    config = HexPlaneConfig(resolution=(4, 5, 6, 3), multires=(1, 3), features=2)
    field = config.build(BOX)
    planes = field.planes()
    assert len(planes.spatial) == 6 and len(planes.temporal) == 6
    for s, m in enumerate(config.multires):
        rx, ry, rz = 4 * m, 5 * m, 6 * m
        xy, xz, yz = planes.spatial[3 * s : 3 * s + 3]
        xt, yt, zt = planes.temporal[3 * s : 3 * s + 3]
        assert (xy.shape, xz.shape, yz.shape) == ((2, ry, rx), (2, rz, rx), (2, rz, ry))
        # Time is never multiplied and runs along dim -2.
        assert (xt.shape, yt.shape, zt.shape) == ((2, 3, rx), (2, 3, ry), (2, 3, rz))
    # Every plane is a view of one slot of a registered Parameter, and every slot of every
    # Parameter is exactly one plane.
    slots = [_locate(field, plane) for plane in planes.spatial + planes.temporal]
    assert len(set(slots)) == 12
    assert sorted(slots) == sorted(
        (name, slot) for name, p in field.named_parameters() for slot in range(p.shape[0])
    )
    params = list(field.parameters())
    # A regularizer's gradient on the views reaches every Parameter.
    torch.stack(
        [(p - 0.7).square().sum() for p in planes.spatial + planes.temporal]
    ).sum().backward()
    for p in params:
        assert p.grad is not None and bool((p.grad != 0).all())


def test_cubic_grid_groups_planes_of_equal_shape() -> None:
    # Without data to size it, a scale is two Parameters: three 64×64 spatial planes and
    # three 25×64 time planes, 16 features each.
    field = HexPlaneConfig().build(BOX)
    shapes = [tuple(p.shape) for p in field.parameters()]
    assert shapes == [(3, 16, 64, 64), (3, 16, 25, 64), (3, 16, 128, 128), (3, 16, 25, 128)]
    assert field.out_dim == 32


def test_initialisation() -> None:
    g = torch.Generator().manual_seed(3)
    field = HexPlaneConfig(resolution=(5, 6, 7, 4), init_range=(0.2, 0.3)).build(BOX, generator=g)
    planes = field.planes()
    for plane in planes.temporal:
        assert bool((plane == 1).all())
    for plane in (p.detach() for p in planes.spatial):
        assert float(plane.min()) >= 0.2 and float(plane.max()) <= 0.3
        assert float(plane.std()) > 0.01
    again = HexPlaneConfig(resolution=(5, 6, 7, 4), init_range=(0.2, 0.3)).build(
        BOX, generator=torch.Generator().manual_seed(3)
    )
    for a, b in zip(field.parameters(), again.parameters(), strict=True):
        assert torch.equal(a, b)


def test_static_at_initialisation_then_dynamic() -> None:
    g = torch.Generator().manual_seed(4)
    field = HexPlaneConfig(resolution=(8, 8, 8, 6), multires=(1, 2), features=4).build(BOX)
    xyz = _points(200, BOX, g, torch.float32)
    base = field(xyz, torch.zeros(200, 1))
    for time in (0.13, 0.5, 0.999, 1.0, -3.0, 7.0):
        assert torch.equal(field(xyz, torch.full((200, 1), time)), base)
    # The initial feature is the purely spatial product xy·xz·yz.
    assert torch.allclose(base, _reference(field, xyz, torch.zeros(200, 1)), rtol=1e-5, atol=0)
    with torch.no_grad():
        field.planes().temporal[1][:, 2, :] += 0.5  # the yt plane at one time row
    with torch.no_grad():
        a, b = field(xyz, torch.full((200, 1), 0.1)), field(xyz, torch.full((200, 1), 0.4))
    assert float((a - b).abs().max()) > 1e-2


def test_matches_reference_bilinear_product() -> None:
    g = torch.Generator().manual_seed(5)
    config = HexPlaneConfig(resolution=(3, 4, 5, 6), multires=(1, 3), features=3)
    field = config.build(BOX, generator=g).double()
    _perturb_time_planes(field, g)
    xyz = _points(50, BOX, g, torch.float64)
    t = torch.rand(50, 1, generator=g, dtype=torch.float64)
    assert torch.allclose(field(xyz, t), _reference(field, xyz, t), rtol=1e-12, atol=1e-12)


@torch.no_grad()
def test_hand_computed_sample_on_a_2x2_grid() -> None:
    box = SceneBox((0.0, 0.0, 0.0), (2.0, 4.0, 8.0))
    field = HexPlaneConfig(resolution=(2, 2, 2, 2), multires=(1,), features=1).build(box)
    field = field.double()
    planes = field.planes()
    with torch.no_grad():
        planes.spatial[0].copy_(torch.tensor([[[1.0, 2.0], [3.0, 4.0]]]))  # xy: rows y, cols x
        planes.spatial[1].fill_(0.5)  # xz
        planes.spatial[2].fill_(2.0)  # yz
    # x = 0.5 → u = -0.5, a quarter of the way along x; y = 3 → three quarters along y.
    xyz = torch.tensor([[0.5, 3.0, 5.0]], dtype=torch.float64)
    t = torch.tensor([[0.5]], dtype=torch.float64)
    xy = (1 * 0.75 + 2 * 0.25) * 0.25 + (3 * 0.75 + 4 * 0.25) * 0.75  # = 2.75
    assert float(field(xyz, t)) == pytest.approx(xy * 0.5 * 2.0, abs=1e-14)
    with torch.no_grad():
        planes.temporal[0].copy_(torch.tensor([[[1.0, 1.0], [1.0, 5.0]]]))  # xt: rows t, cols x
    # Half-way in t, a quarter along x: (1 + (1 + 4·0.25)) / 2 = 1.5.
    assert float(field(xyz, t)) == pytest.approx(xy * 0.5 * 2.0 * 1.5, abs=1e-14)


@torch.no_grad()
def test_box_corners_map_to_grid_corners() -> None:
    res = (3, 4, 5, 2)
    field = HexPlaneConfig(resolution=res, multires=(1,), features=1).build(BOX).double()
    planes = field.planes()
    with torch.no_grad():
        for plane in planes.spatial:  # every texel distinct and positive
            plane.copy_(torch.arange(1, plane.numel() + 1, dtype=torch.float64).view_as(plane))
    xy, xz, yz = (p.detach()[0] for p in planes.spatial)
    for corner in itertools.product((0, 1), repeat=3):
        point = [BOX.upper[i] if c else BOX.lower[i] for i, c in enumerate(corner)]
        xi, yi, zi = (res[i] - 1 if c else 0 for i, c in enumerate(corner))
        expected = xy[yi, xi] * xz[zi, xi] * yz[zi, yi]
        got = field(
            torch.tensor([point], dtype=torch.float64), torch.zeros(1, 1, dtype=torch.float64)
        )
        assert float(got) == pytest.approx(float(expected), rel=1e-12)


def test_outside_the_box_and_time_range_is_clamped() -> None:
    g = torch.Generator().manual_seed(6)
    field = HexPlaneConfig(resolution=(5, 5, 5, 4), multires=(1, 2), features=4).build(BOX)
    field = field.double()
    _perturb_time_planes(field, g)
    lower = torch.tensor(BOX.lower, dtype=torch.float64)
    upper = torch.tensor(BOX.upper, dtype=torch.float64)
    inside = _points(64, BOX, g, torch.float64)
    offset = torch.randn(64, 3, generator=g, dtype=torch.float64) * 5
    outside = (inside + offset).requires_grad_()
    clamped = torch.maximum(torch.minimum(outside.detach(), upper), lower)
    t = torch.rand(64, 1, generator=g, dtype=torch.float64)
    assert torch.equal(field(outside, t), field(clamped, t))
    out = field(outside, t)
    out.sum().backward()
    assert outside.grad is not None and bool(torch.isfinite(outside.grad).all())
    beyond = (outside.detach() < lower) | (outside.detach() > upper)
    assert bool(beyond.any()) and bool((outside.grad[beyond] == 0).all())
    # Time before 0 is time 0; after 1 is time 1.
    assert torch.equal(field(inside, t - 2), field(inside, torch.zeros_like(t)))
    assert torch.equal(field(inside, t + 2), field(inside, torch.ones_like(t)))
    far = torch.tensor([[1e30, -1e30, 3e8]], dtype=torch.float64)
    assert bool(torch.isfinite(field(far, torch.tensor([[1e20]], dtype=torch.float64))).all())


def _locate(field: HexPlaneField, view: Tensor) -> tuple[str, int]:
    """The Parameter that a `planes()` view belongs to, and the view's slot in it."""
    for name, param in field.named_parameters():
        if view._base is param:
            return name, (view.storage_offset() - param.storage_offset()) // view.numel()
    raise AssertionError("plane is not a view of a Parameter")


def test_gradients_reach_every_plane_and_the_inputs() -> None:
    g = torch.Generator().manual_seed(7)
    config = HexPlaneConfig(resolution=(6, 7, 8, 5), multires=(1, 2), features=4)
    field = config.build(BOX)
    xyz = _points(300, BOX, g, torch.float32).requires_grad_()
    t = torch.rand(300, 1, generator=g).requires_grad_()
    field(xyz, t).square().sum().backward()
    params = dict(field.named_parameters())
    for name, p in params.items():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()), name
    planes = field.planes()
    for view in planes.spatial + planes.temporal:
        name, slot = _locate(field, view)
        grad = params[name].grad
        assert grad is not None and float(grad[slot].abs().sum()) > 0, (name, slot)
    assert xyz.grad is not None and bool(torch.isfinite(xyz.grad).all())
    assert bool((xyz.grad.abs().sum(0) > 0).all())
    # At initialisation the time planes are exactly 1, so d feature / d t is exactly 0.
    assert t.grad is not None and bool((t.grad == 0).all())
    # Once a time plane departs from 1, t gets a gradient too.
    _perturb_time_planes(field, g)
    t.grad = None
    field(xyz, t).square().sum().backward()
    assert t.grad is not None and float(t.grad.abs().sum()) > 0


@pytest.mark.parametrize(
    ("resolution", "multires", "features"),
    [((2, 2, 2, 2), (1,), 4), ((1, 1, 1, 1), (1,), 2), ((2, 3, 2, 2), (1, 2, 4), 3)],
)
def test_very_small_grids(
    resolution: tuple[int, int, int, int], multires: tuple[int, ...], features: int
) -> None:
    g = torch.Generator().manual_seed(9)
    config = HexPlaneConfig(resolution=resolution, multires=multires, features=features)
    field = config.build(BOX)
    _perturb_time_planes(field, g)
    xyz = _points(33, BOX, g, torch.float32).requires_grad_()
    t = torch.rand(33, 1, generator=g)
    out = field(xyz, t)
    assert out.shape == (33, features * len(multires))
    assert bool(torch.isfinite(out).all())
    out.sum().backward()
    assert xyz.grad is not None and bool(torch.isfinite(xyz.grad).all())


def test_a_2x2x2x2_grid_is_one_spatial_and_one_time_parameter() -> None:
    field = HexPlaneConfig(resolution=(2, 2, 2, 2), multires=(1,), features=4).build(BOX)
    assert [tuple(p.shape) for p in field.parameters()] == [(3, 4, 2, 2), (3, 4, 2, 2)]
    xyz = _points(10, BOX, torch.Generator().manual_seed(10), torch.float32)
    assert torch.equal(field(xyz, torch.zeros(10, 1)), field(xyz, torch.ones(10, 1)))


def test_very_large_grid() -> None:
    g = torch.Generator().manual_seed(11)
    config = HexPlaneConfig(resolution=(1024, 768, 1024, 300), multires=(1,), features=2)
    field = config.build(BOX)
    xyz = _points(2000, BOX, g, torch.float32).requires_grad_()
    out = field(xyz, torch.rand(2000, 1, generator=g))
    assert out.shape == (2000, 2) and bool(torch.isfinite(out).all())
    out.sum().backward()
    assert xyz.grad is not None and bool(torch.isfinite(xyz.grad).all())
    assert all(
        p.grad is not None and bool(torch.isfinite(p.grad).all()) for p in field.parameters()
    )


def _interior_points(field: HexPlaneField, n: int, generator: torch.Generator) -> Tensor:
    """Points at least 0.05 texel away from every cell boundary of every scale and axis, so
    that the bilinear interpolation is smooth around them and gradcheck's differences hold."""
    box, config = field.box, field.config
    assert config.resolution is not None  # a built field has its resolution resolved
    chosen: list[list[float]] = []
    while len(chosen) < n:
        unit = torch.rand(3, generator=generator, dtype=torch.float64) * 1.8 - 0.9
        ok = True
        for m in config.multires:
            for axis in range(3):
                texel = (float(unit[axis]) + 1) / 2 * (config.resolution[axis] * m - 1)
                ok &= 0.05 < texel % 1 < 0.95
        if ok:
            chosen.append([box.lower[i] + (float(unit[i]) + 1) / 2 * box.size[i] for i in range(3)])
    return torch.tensor(chosen, dtype=torch.float64)


def test_gradcheck_wrt_a_plane_xyz_and_t() -> None:
    g = torch.Generator().manual_seed(12)
    config = HexPlaneConfig(resolution=(3, 4, 3, 3), multires=(1, 2), features=2)
    field = config.build(BOX, generator=g).double()
    _perturb_time_planes(field, g)
    xyz = _interior_points(field, 6, g).requires_grad_()
    # Away from the time texel boundaries (-1, 0, 1 in field units) too.
    t = torch.tensor([[0.1], [0.3], [0.45], [0.6], [0.8], [0.9]], dtype=torch.float64)
    name, _ = _locate(field, field.planes().temporal[-1])  # the finest scale's zt plane
    plane = dict(field.named_parameters())[name].detach().clone().requires_grad_()

    def sample(weights: Tensor, points: Tensor, times: Tensor) -> Tensor:
        return torch.func.functional_call(field, {name: weights}, (points, times))

    assert torch.autograd.gradcheck(sample, (plane, xyz, t.requires_grad_()), eps=1e-6, atol=1e-8)


def test_gradcheck_through_the_spatial_planes() -> None:
    g = torch.Generator().manual_seed(13)
    field = HexPlaneConfig(resolution=(3, 3, 3, 4), multires=(1,), features=2).build(BOX).double()
    _perturb_time_planes(field, g)
    xyz = _interior_points(field, 5, g)
    t = torch.rand(5, 1, generator=g, dtype=torch.float64)
    name, _ = _locate(field, field.planes().spatial[0])
    spatial = dict(field.named_parameters())[name]
    assert spatial.shape == (3, 2, 3, 3)  # xy, xz and yz together

    def sample(weights: Tensor) -> Tensor:
        return torch.func.functional_call(field, {name: weights}, (xyz, t))

    assert torch.autograd.gradcheck(sample, (spatial.detach().clone().requires_grad_(),))


def test_state_dict_round_trip_holds_only_the_planes_and_their_extent() -> None:
    g = torch.Generator().manual_seed(14)
    config = HexPlaneConfig(resolution=(4, 5, 6, 3), multires=(1, 2), features=3)
    field = config.build(BOX, generator=g)
    _perturb_time_planes(field, g)
    state = field.state_dict()
    assert all(key.startswith("grids.") or key == "extent" for key in state)
    other = config.build(BOX)
    other.load_state_dict(state)
    xyz = _points(20, BOX, g, torch.float32)
    t = torch.rand(20, 1, generator=g)
    assert torch.equal(field(xyz, t), other(xyz, t))


@pytest.mark.parametrize("device", DEVICES)
def test_device(device: str) -> None:
    g = torch.Generator().manual_seed(15)
    field = HexPlaneConfig(resolution=(5, 6, 7, 4), features=4).build(BOX)
    _perturb_time_planes(field, g)
    xyz = _points(40, BOX, g, torch.float32)
    t = torch.rand(40, 1, generator=g)
    expected = field(xyz, t)
    moved = field.to(device)
    got = moved(xyz.to(device), t.to(device))
    assert got.device.type == torch.device(device).type
    assert torch.allclose(got.cpu(), expected, atol=1e-6)


@pytest.mark.parametrize("device", DEVICES)
def test_crop_keeps_the_values_inside_on_every_device(device: str) -> None:
    # Cropping ends every training run; on a GPU it once mixed a CUDA extent with CPU node
    # arithmetic and failed there alone. The cropped field must still agree with the full one
    # at the points it was cropped to, on the field's own device.
    g = torch.Generator().manual_seed(16)
    field = HexPlaneConfig(resolution=(9, 9, 9, 4), features=4).build(BOX)
    _perturb_time_planes(field, g)
    with torch.no_grad():
        for plane in field.planes().spatial:
            plane.add_(0.3 * torch.randn(plane.shape, generator=g, dtype=plane.dtype))
    lower, size = torch.tensor(BOX.lower), torch.tensor(BOX.size)
    inner = lower + size * (0.3 + 0.3 * torch.rand(40, 3, generator=g))  # a middle sub-box
    t = torch.rand(40, 1, generator=g)
    expected = field(inner, t)
    moved = field.to(device)
    assert moved.crop_to(inner.to(device)) is not None
    assert moved.extent.device.type == torch.device(device).type
    got = moved(inner.to(device), t.to(device))
    torch.testing.assert_close(got.cpu(), expected, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"resolution": (4, 4, 0, 4)},
        {"multires": ()},
        {"multires": (1, 0)},
        {"features": 0},
        {"init_range": (0.5, 0.1)},
        {"init_range": (0.0, float("inf"))},
    ],
)
def test_config_rejects_bad_values(kwargs: dict[str, object]) -> None:
    with pytest.raises(ConfigError, match=r"--field\."):
        HexPlaneConfig(**kwargs)  # type: ignore[arg-type]

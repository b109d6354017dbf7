"""The compiled plane sampler (`sample_group` on the CPU) against its definition,
`reference_sample` (`F.grid_sample`, bilinear, border, align_corners=True): values and
gradients to rounding in float64 and float32, at the grid's edges and corners, for time
planes (shift 1), at any thread count, and inside the field."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import Tensor

from dyngs.fields import HexPlaneConfig
from dyngs.fields import hexplane as hp
from dyngs.fields import plane_sampler as ps
from dyngs.types import SceneBox

pytest.importorskip("numba")

COLUMNS = torch.tensor([0, 1, 0, 2, 1, 2])  # xy, xz, yz
TIME_COLUMNS = torch.tensor([0, 3, 1, 3, 2, 3])  # xt, yt, zt


def _case(
    shape: tuple[int, int, int, int], n: int, dtype: torch.dtype, seed: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Planes, coordinates in [-1, 1] with the edges and corners among them, and an
    upstream gradient."""
    generator = torch.Generator().manual_seed(seed)
    planes = torch.randn(shape, generator=generator, dtype=dtype)
    coords = torch.rand(n, 4, generator=generator, dtype=dtype) * 2 - 1
    edges = torch.tensor([[-1.0, -1.0, -1.0, -1.0], [1.0, 1.0, 1.0, 1.0], [-1.0, 1.0, 0.0, 1.0],
                          [1.0, -1.0, 1.0, 0.0], [0.0, 0.0, 0.0, 0.0]], dtype=dtype)  # fmt: skip
    coords[: min(n, len(edges))] = edges[:n]
    upstream = torch.randn(shape[0], shape[1], 1, n, generator=generator, dtype=dtype)
    return planes, coords, upstream


def _run(
    sample, planes: Tensor, coords: Tensor, columns: Tensor, shift: float, upstream: Tensor
) -> tuple[Tensor, Tensor, Tensor]:  # type: ignore[no-untyped-def]
    p = planes.clone().requires_grad_(True)
    c = coords.clone().requires_grad_(True)
    out = sample(p, c, columns, shift)
    out.backward(upstream)
    assert p.grad is not None and c.grad is not None
    return out.detach(), p.grad, c.grad


def _close(a: Tensor, b: Tensor, relative: float) -> None:
    """|a − b| within `relative` of b's largest entry."""
    scale = max(float(b.abs().max()), 1e-30)
    assert float((a - b).abs().max()) <= relative * scale


SHAPES = [(3, 8, 5, 7), (3, 16, 13, 35), (3, 32, 35, 35), (2, 8, 1, 9), (1, 24, 2, 2)]


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("shift", [0.0, 1.0])
def test_float64_is_grid_sample_to_rounding(shape: tuple[int, int, int, int], shift: float) -> None:
    columns = (COLUMNS if shift == 0.0 else TIME_COLUMNS)[: 2 * shape[0]]
    planes, coords, upstream = _case(shape, 300, torch.float64, seed=sum(shape))
    assert ps.compiled_usable(planes, coords)
    fast = _run(ps.sample_group, planes, coords, columns, shift, upstream)
    slow = _run(ps.reference_sample, planes, coords, columns, shift, upstream)
    for a, b in zip(fast, slow, strict=True):
        _close(a, b, 1e-12)


@pytest.mark.parametrize("shape", SHAPES[:3])
def test_float32_is_grid_sample_to_rounding(shape: tuple[int, int, int, int]) -> None:
    planes, coords, upstream = _case(shape, 2000, torch.float32, seed=3)
    fast = _run(ps.sample_group, planes, coords, COLUMNS, 0.0, upstream)
    slow = _run(ps.reference_sample, planes, coords, COLUMNS, 0.0, upstream)
    for a, b in zip(fast, slow, strict=True):
        _close(a, b, 1e-5)


def test_the_edges_hold_the_coordinate_gradient_at_zero_as_border_padding_does() -> None:
    planes, _, upstream = _case((3, 8, 6, 6), 4, torch.float64, seed=1)
    rows = [[-1.0, 0.3, -0.2, 0.0], [1.0, -0.4, 0.5, 0.0], [0.1, -1.0, 1.0, 0.0]]
    rows.append([0.2, 0.3, 0.4, 0.0])  # inside
    coords = torch.tensor(rows, dtype=torch.float64)
    _, _, fast = _run(ps.sample_group, planes, coords, COLUMNS, 0.0, upstream)
    _, _, slow = _run(ps.reference_sample, planes, coords, COLUMNS, 0.0, upstream)
    assert fast[0, 0] == 0 and fast[1, 0] == 0 and fast[2, 1] == 0 and fast[2, 2] == 0
    assert (fast[3, :3] != 0).all()  # inside, every column it reads has a gradient
    _close(fast, slow, 1e-12)


def test_a_time_plane_of_ones_gives_exactly_one() -> None:
    planes = torch.ones(3, 16, 9, 12)
    coords = torch.rand(500, 4, generator=torch.Generator().manual_seed(0)) * 2 - 1
    out = ps.sample_group(planes, coords, TIME_COLUMNS, 1.0)
    assert bool((out == 1.0).all())


def test_gradcheck_in_float64() -> None:
    planes, _, _ = _case((2, 8, 4, 5), 6, torch.float64, seed=5)
    # Inside the grid and off its nodes, where the bilinear form has its kinks.
    coords = torch.rand(6, 4, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    coords = coords * 1.8 - 0.9
    planes.requires_grad_(True)
    coords.requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda p, c: ps.sample_group(p, c, COLUMNS[:4], 1.0), (planes, coords)
    )


def test_the_same_to_the_bit_at_any_thread_count() -> None:
    planes, coords, upstream = _case((3, 32, 20, 20), 3000, torch.float32, seed=2)
    before = torch.get_num_threads()
    try:
        results = []
        for threads in (1, 2, 3):
            torch.set_num_threads(threads)
            results.append(_run(ps.sample_group, planes, coords, COLUMNS, 0.0, upstream))
    finally:
        torch.set_num_threads(before)
    for other in results[1:]:
        for a, b in zip(results[0], other, strict=True):
            assert torch.equal(a, b)


def test_the_planes_gradient_alone_is_the_same_without_the_coordinates() -> None:
    """Coordinates that need no gradient skip the backward's coordinate jobs; the planes'
    gradient is the same to the bit, and the reference's to rounding."""
    planes, coords, upstream = _case((3, 16, 13, 35), 700, torch.float64, seed=4)
    _, with_coords, _ = _run(ps.sample_group, planes, coords, TIME_COLUMNS, 1.0, upstream)
    p = planes.clone().requires_grad_(True)
    ps.sample_group(p, coords, TIME_COLUMNS, 1.0).backward(upstream)
    assert p.grad is not None
    assert torch.equal(p.grad, with_coords)
    _, reference, _ = _run(ps.reference_sample, planes, coords, TIME_COLUMNS, 1.0, upstream)
    _close(p.grad, reference, 1e-12)


def _span_areas(spans: Tensor) -> Tensor:
    """Each plane's span's node count, from `_placed`'s spans."""
    return (spans[:, 1] + 1 - spans[:, 0]) * (spans[:, 3] + 1 - spans[:, 2])


def _kernel_gradient(
    planes: Tensor, coords: Tensor, upstream: Tensor, block: int, spans: Tensor, slots: Tensor
) -> Tensor:
    """The planes' gradient straight from `sampler_kernels.sample_backward` (shift 0, no
    coordinates' gradient), every entry NaN until the kernel writes it."""
    from dyngs.fields import sampler_kernels as sk

    height, width = planes.shape[2:]
    values = planes.permute(0, 2, 3, 1).contiguous()
    nodes, fractions, _, _ = ps._placed(planes, coords, COLUMNS)
    scales = np.array([(width - 1) / 2, (height - 1) / 2], dtype=np.float32)
    grad = torch.full_like(planes, float("nan"))
    sk.sample_backward(values.numpy(), nodes.numpy(), fractions.numpy(), np.float32(1), scales,
                       ps.channels_last(upstream).numpy(), block, spans.numpy(), slots.numpy(),
                       grad.numpy(), torch.empty(0, 3, 2).numpy())  # fmt: skip
    return grad


def test_the_plane_jobs_block_changes_no_digit() -> None:
    """Each plane node adds its points in the same order at any block of channels a job
    takes: 8 or 16 give the same gradient to the bit (`sampler_kernels.plane_block` picks
    between them for speed alone)."""
    from dyngs.fields import sampler_kernels as sk

    planes, coords, upstream = _case((3, 32, 13, 35), 2000, torch.float32, seed=6)
    _, _, spans, slots = ps._placed(planes, coords, COLUMNS)
    grads = [
        _kernel_gradient(planes, coords, upstream, block, spans, slots)
        for block in (ps.BLOCK, sk.WIDE_BLOCK)
    ]
    assert bool(grads[0].isfinite().all())  # every entry written
    assert torch.equal(grads[0], grads[1])
    assert [sk.plane_block(c) for c in (8, 16, 24, 32, 48, 64)] == [8, 8, 8, 16, 16, 16]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_points_in_a_corner_of_the_planes(dtype: torch.dtype) -> None:
    """Points that read a few nodes of large planes (a real capture's moving part): the
    compiled path copies and adds only the span of nodes they read (or only the nodes
    read, where they are few), and the planes' gradient is zero everywhere else, as the
    reference's is. One span reaches the last node (x1 = x0 there), one the first."""
    planes, coords, upstream = _case((3, 16, 40, 50), 300, dtype, seed=7)
    generator = torch.Generator().manual_seed(8)
    coords = 0.2 * torch.rand(300, 4, generator=generator, dtype=dtype) + 0.5
    coords[:5, 0] = 1.0  # the last node along x of the planes reading column 0
    coords[5:9, 2] = -1.0  # the first node of those reading column 2
    fast = _run(ps.sample_group, planes, coords, COLUMNS, 0.0, upstream)
    slow = _run(ps.reference_sample, planes, coords, COLUMNS, 0.0, upstream)
    for a, b in zip(fast, slow, strict=True):
        _close(a, b, 1e-12 if dtype == torch.float64 else 1e-5)
    grad = fast[1]
    assert bool((grad[0, :, :20] == 0).all())  # rows no point of plane 0 reads
    assert bool((grad[0, :, :, :30] == 0).all())  # columns no point of plane 0 reads
    assert bool((grad[1, :, 0] != 0).any())  # the first row, which plane 1 reads
    assert bool((grad[0, :, :, -1] != 0).any())  # the last column, which plane 0 reads
    _, _, spans, slots = ps._placed(planes, coords, COLUMNS)
    assert spans[0, 1] == 49 and spans[1, 2] == 0  # the last x node, the first y node
    for g in range(3):  # the nodes read are numbered 1 … their count, once each
        numbers = slots[g][slots[g] > 0].sort().values
        assert numbers.tolist() == list(range(1, int(spans[g, 4]) + 1))
    # Both ways of copying ran: a plane whose points read few of its span's nodes, node by
    # node, and one whose points read many, row by row.
    from dyngs.fields.sampler_kernels import SPARSE

    sparse = spans[:, 4] * SPARSE < _span_areas(spans)
    assert bool(sparse.any()) and not bool(sparse.all())


def test_the_sparse_planes_gradient_is_the_span_ones_to_the_bit() -> None:
    """A plane's nodes add their points in the same order gathered node by node as in the
    span's buffer: forcing the span's way (a node count that is not sparse) changes no
    digit."""
    from dyngs.fields import sampler_kernels as sk

    # 100 points on 60 × 70 planes read some 400 of a plane's 4 200 nodes.
    planes, coords, upstream = _case((3, 16, 60, 70), 100, torch.float32, seed=9)
    _, _, spans, slots = ps._placed(planes, coords, COLUMNS)
    area = _span_areas(spans)
    assert bool((spans[:, 4] * sk.SPARSE < area).all())
    dense = spans.clone()
    dense[:, 4] = area  # never sparse
    grads = [
        _kernel_gradient(planes, coords, upstream, 16, given, slots) for given in (spans, dense)
    ]
    assert bool(grads[0].isfinite().all())
    assert torch.equal(grads[0], grads[1])


def test_the_span_of_no_points_is_empty() -> None:
    planes, coords, _ = _case((3, 8, 5, 5), 0, torch.float32, seed=0)
    _, _, spans, slots = ps._placed(planes, coords, COLUMNS)
    assert spans.tolist() == [[0, -1, 0, -1, 0]] * 3 and not bool(slots.any())


def test_channels_that_are_not_a_block_use_the_reference() -> None:
    planes, coords, _ = _case((3, 12, 5, 5), 10, torch.float32, seed=0)
    assert not ps.compiled_usable(planes, coords)
    assert torch.equal(
        ps.sample_group(planes, coords, COLUMNS, 0.0),
        ps.reference_sample(planes, coords, COLUMNS, 0.0),
    )


def test_no_points() -> None:
    planes, coords, upstream = _case((3, 8, 5, 5), 0, torch.float64, seed=0)
    out, grad, coords_grad = _run(ps.sample_group, planes, coords, COLUMNS, 0.0, upstream)
    assert out.shape == (3, 8, 1, 0) and coords_grad.shape == (0, 4)
    assert bool((grad == 0).all())


@pytest.mark.parametrize("cropped", [False, True])
def test_the_field_is_its_reference_to_rounding(
    monkeypatch: pytest.MonkeyPatch, cropped: bool
) -> None:
    """The whole field (both scales, spatial and time groups, a cut field's local
    coordinates) with the compiled sampler, against the same field with grid_sample."""
    box = SceneBox((-1.0, -2.0, 0.5), (2.0, 1.0, 4.5))
    config = HexPlaneConfig(resolution=(9, 7, 8, 5), multires=(1, 2), features=16)
    field = hp.HexPlaneField(config, box, generator=torch.Generator().manual_seed(0)).double()
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():  # time planes away from 1, so that they matter
        for grid in field.grids:
            grid.add_(0.1 * torch.randn(grid.shape, generator=generator, dtype=grid.dtype))
    xyz = torch.rand(400, 3, generator=generator, dtype=torch.float64) * 3 - 1.5
    xyz[:, 2] += 2.5
    t = torch.rand(400, 1, generator=generator, dtype=torch.float64)
    if cropped:
        assert field.crop_to(xyz[:200] * 0.5 + torch.tensor([0.2, -0.4, 1.3])) is not None
    upstream = torch.randn(400, field.out_dim, generator=generator, dtype=torch.float64)

    def gradients() -> list[Tensor]:
        field.zero_grad(set_to_none=True)
        points = xyz.clone().requires_grad_(True)
        out = field(points, t)
        out.backward(upstream)
        assert points.grad is not None
        return [out.detach(), points.grad, *(g.grad for g in field.grids)]

    fast = gradients()
    monkeypatch.setattr(hp, "sample_group", ps.reference_sample)
    slow = gradients()
    for a, b in zip(fast, slow, strict=True):
        _close(a, b, 1e-12)

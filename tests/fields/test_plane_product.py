"""The compiled plane product (`compiled_products`) against its PyTorch reference
(`plane_products`): the same values and gradients to the bit, alone and inside the field,
for every grouping of the planes, both float dtypes, any thread count and no points."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from dyngs.fields import HexPlaneConfig
from dyngs.fields import hexplane as hp
from dyngs.types import SceneBox

pytest.importorskip("numba")

BOX = SceneBox((-1.0, -2.0, 0.5), (2.0, 1.0, 4.5))


def _samples(
    layout: list[list[int]], channels: int, n: int, dtype: torch.dtype, seed: int
) -> list[list[Tensor]]:
    """Per scale, groups of [G, F, 1, N] samples (G from `layout`), values around 1 with
    both signs, as the field's planes give them."""
    generator = torch.Generator().manual_seed(seed)
    return [
        [
            (
                1 + 0.5 * torch.randn(g, channels, 1, n, generator=generator, dtype=dtype)
            ).requires_grad_(True)
            for g in groups
        ]
        for groups in layout
    ]


def _run(combine, samples: list[list[Tensor]], weights: Tensor) -> tuple[Tensor, list[Tensor]]:  # type: ignore[no-untyped-def]
    for groups in samples:
        for sampled in groups:
            sampled.grad = None
    out = combine(samples)
    (out * weights).sum().backward()
    grads = [sampled.grad for groups in samples for sampled in groups]
    assert all(grad is not None for grad in grads)
    return out.detach(), grads  # type: ignore[return-value]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    "layout",
    [[[3, 3]], [[3, 3], [3, 3]], [[1, 2, 1, 2], [3, 3], [2, 1, 3]], [[1, 1, 1, 1, 1, 1]]],
)
def test_compiled_products_are_the_reference_to_the_bit(
    dtype: torch.dtype, layout: list[list[int]]
) -> None:
    samples = _samples(layout, channels=7, n=301, dtype=dtype, seed=len(layout))
    weights = torch.randn(301, 7 * len(layout), dtype=dtype)
    out, grads = _run(hp.plane_products, samples, weights)
    fast_out, fast_grads = _run(hp.compiled_products, samples, weights)
    assert fast_out.shape == out.shape == (301, 7 * len(layout))
    assert torch.equal(fast_out, out)
    for fast, reference in zip(fast_grads, grads, strict=True):
        assert fast.shape == reference.shape
        assert torch.equal(fast, reference)


def test_compiled_products_are_the_same_at_any_thread_count() -> None:
    samples = _samples([[3, 3], [3, 3]], channels=16, n=2000, dtype=torch.float32, seed=3)
    weights = torch.randn(2000, 32)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = _run(hp.compiled_products, samples, weights)
        torch.set_num_threads(2)
        two = _run(hp.compiled_products, samples, weights)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one[0], two[0])
    assert all(torch.equal(a, b) for a, b in zip(one[1], two[1], strict=True))


def test_no_points() -> None:
    samples = _samples([[3, 3], [3, 3]], channels=4, n=0, dtype=torch.float32, seed=0)
    out, grads = _run(hp.compiled_products, samples, torch.zeros(0, 8))
    assert out.shape == (0, 8)
    assert all(g.shape == (3, 4, 1, 0) for g in grads)


def test_gradcheck() -> None:
    samples = _samples([[3, 3]], channels=2, n=5, dtype=torch.float64, seed=1)
    flat = [sampled for groups in samples for sampled in groups]
    assert torch.autograd.gradcheck(lambda *f: hp.compiled_products([list(f)]), flat)


@pytest.mark.parametrize("resolution", [(9, 9, 9, 5), (8, 11, 6, 4)])
def test_the_field_is_the_same_through_either_product(
    monkeypatch: pytest.MonkeyPatch, resolution: tuple[int, int, int, int]
) -> None:
    """The whole field, forward and backward to its planes and the points, on a cubic grid
    (two plane groups a scale) and a grid of three spatial sizes (four)."""
    generator = torch.Generator().manual_seed(5)
    field = HexPlaneConfig(resolution=resolution, features=6).build(BOX, generator=generator)
    with torch.no_grad():
        for grid in field.grids:
            grid.add_(0.2 * torch.randn(grid.shape, generator=generator))
    lower, size = torch.tensor(BOX.lower), torch.tensor(BOX.size)
    xyz = lower + torch.rand(500, 3, generator=generator) * size
    t = torch.rand(500, 1, generator=generator)
    weights = torch.randn(500, field.out_dim, generator=generator)

    def run() -> tuple[Tensor, Tensor, list[Tensor]]:
        field.zero_grad()
        points = xyz.clone().requires_grad_(True)
        out = field(points, t)
        (out * weights).sum().backward()
        assert points.grad is not None
        return out.detach(), points.grad, [grid.grad.clone() for grid in field.grids]

    fast = run()
    monkeypatch.setattr(hp, "compiled_products", hp.plane_products)
    reference = run()
    assert torch.equal(fast[0], reference[0])
    assert torch.equal(fast[1], reference[1])
    assert all(torch.equal(a, b) for a, b in zip(fast[2], reference[2], strict=True))

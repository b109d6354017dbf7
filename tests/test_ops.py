"""The fast finiteness checks of dyngs/ops.py against `torch.isfinite`, their definition."""

from __future__ import annotations

import math

import pytest
import torch

from dyngs.ops import finite_rows, finite_rows_by_row, zero_nonfinite

SPECIALS = [math.inf, -math.inf, math.nan]


def _poisoned(shape: tuple[int, ...], dtype: torch.dtype, seed: int) -> torch.Tensor:
    """Random values with the extremes of the dtype, ±0, and ±Inf/NaN scattered in."""
    generator = torch.Generator().manual_seed(seed)
    x = torch.randn(shape, dtype=dtype, generator=generator)
    flat = x.view(-1)
    if flat.numel() == 0:
        return x
    info = torch.finfo(dtype)
    extremes = [info.max, -info.max, info.tiny, info.tiny / 4, 0.0, -0.0]
    picks = torch.randint(0, flat.numel(), (len(extremes) + 6,), generator=generator).tolist()
    for position, value in zip(picks, extremes + SPECIALS * 2, strict=True):
        flat[position] = value
    return x


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", range(4))
def test_finite_rows_is_isfinite_all(dtype: torch.dtype, seed: int) -> None:
    n = 40
    tensors = [
        _poisoned((n, 3), dtype, seed),
        _poisoned((n,), torch.float32, seed + 10),
        _poisoned((n, 4, 3), dtype, seed + 20),
        torch.zeros(n, 0, dtype=dtype),
    ]
    expected = torch.ones(n, dtype=torch.bool)
    for t in tensors:
        expected &= torch.isfinite(t.reshape(n, -1)).all(dim=1)
    assert 0 < int(expected.sum()) < n  # the case has rows of both kinds
    assert torch.equal(finite_rows(*tensors), expected)


def test_finite_rows_of_huge_finite_rows_and_of_empty_inputs() -> None:
    """A row of the largest finite values is finite (x·0 cannot overflow, where a sum of x
    would); an empty scene has no rows; a row of width 0 is finite."""
    big = torch.full((2, 5), torch.finfo(torch.float32).max)
    assert finite_rows(big).tolist() == [True, True]
    assert finite_rows(torch.zeros(0, 3), torch.zeros(0)).shape == (0,)
    assert finite_rows(torch.zeros(3, 0)).tolist() == [True, True, True]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("special", SPECIALS)
def test_one_nonfinite_entry_anywhere_is_found(dtype: torch.dtype, special: float) -> None:
    """The whole-tensor test that lets clean tensors skip the row-wise one must see a
    single NaN or ±Inf wherever it sits: at either end, at the edges of vector lanes, in
    any tensor of several; with the largest finite values beside it."""
    n = 257
    generator = torch.Generator().manual_seed(7)
    shapes = [(n, 3), (n,), (n, 15, 3)]
    for which, shape in enumerate(shapes):
        size = math.prod(shape)
        for position in sorted({0, 1, 7, 8, 15, 16, 31, 32, size // 2, size - 1}):
            tensors = [torch.randn(s, dtype=dtype, generator=generator) for s in shapes]
            tensors[0][0, 0] = torch.finfo(dtype).max
            tensors[which].view(-1)[position] = special
            row = position // (size // n)
            found = finite_rows(*tensors)
            assert torch.equal(found, finite_rows_by_row(*tensors))
            assert not found[row] and int(found.sum()) == n - 1


def test_clean_tensors_are_finite_in_every_row() -> None:
    tensors = [torch.randn(33, 4, dtype=torch.float64), torch.randn(33), torch.zeros(33, 0)]
    assert finite_rows(*tensors).tolist() == [True] * 33
    assert torch.equal(finite_rows(*tensors), finite_rows_by_row(*tensors))


def test_finite_rows_has_no_gradient() -> None:
    x = torch.randn(4, 3, requires_grad=True)
    assert not finite_rows(x).requires_grad


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_zero_nonfinite_is_where_isfinite(dtype: torch.dtype) -> None:
    base = _poisoned((50, 4), dtype, seed=3)
    fast_input = base.clone().requires_grad_()
    slow_input = base.clone().requires_grad_()
    fast = zero_nonfinite(fast_input)
    slow = torch.where(torch.isfinite(slow_input), slow_input, 0.0)
    assert torch.equal(fast, slow)
    weights = torch.linspace(-1, 2, base.numel(), dtype=dtype).view_as(base)
    (fast * weights).sum().backward()
    (slow * weights).sum().backward()
    assert fast_input.grad is not None and slow_input.grad is not None
    assert torch.equal(fast_input.grad, slow_input.grad)

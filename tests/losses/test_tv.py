"""Total variation of spatial planes on ramps with known answers."""

from __future__ import annotations

import pytest
import torch

from dyngs.losses.tv import plane_tv


def _ramp(a: float, b: float, f: int = 2, r1: int = 4, r0: int = 5) -> torch.Tensor:
    """plane[f, i, j] = a·j + b·i: steps of a along R0 and b along R1."""
    i = torch.arange(r1, dtype=torch.float64)[:, None]
    j = torch.arange(r0, dtype=torch.float64)[None, :]
    return (a * j + b * i).expand(f, r1, r0).clone()


def test_ramp_costs_the_squared_steps() -> None:
    assert plane_tv([_ramp(0.5, 0.0)]).item() == pytest.approx(0.25)
    assert plane_tv([_ramp(0.0, 3.0)]).item() == pytest.approx(9.0)
    assert plane_tv([_ramp(0.5, 3.0)]).item() == pytest.approx(9.25)


def test_mean_over_planes() -> None:
    constant = torch.full((3, 6, 2), 7.0, dtype=torch.float64)
    assert plane_tv([_ramp(2.0, 0.0), constant]).item() == pytest.approx(4.0 / 2)


def test_alternating_plane() -> None:
    # ±1 checkerboard: every neighbour step is 2 → 4 per axis.
    i, j = torch.meshgrid(torch.arange(4), torch.arange(3), indexing="ij")
    plane = ((i + j) % 2 * 2 - 1).double()[None]
    assert plane_tv([plane]).item() == pytest.approx(8.0)


def test_single_cell_axis_costs_nothing() -> None:
    assert plane_tv([_ramp(1.0, 5.0, r1=1)]).item() == pytest.approx(1.0)
    assert plane_tv([torch.ones(4, 1, 1)]).item() == 0.0


def test_empty_list_is_a_zero_tensor() -> None:
    value = plane_tv([])
    assert isinstance(value, torch.Tensor) and value.shape == () and value.item() == 0.0
    (value + plane_tv([_ramp(1.0, 0.0).requires_grad_()])).backward()


def test_gradient_reaches_every_plane() -> None:
    gen = torch.Generator().manual_seed(0)
    planes = [torch.rand(4, 8, 8, generator=gen).requires_grad_() for _ in range(3)]
    plane_tv(planes).backward()
    for p in planes:
        assert p.grad is not None and p.grad.abs().sum() > 0


def test_result_keeps_dtype() -> None:
    assert plane_tv([torch.rand(2, 3, 3, dtype=torch.float64)]).dtype == torch.float64

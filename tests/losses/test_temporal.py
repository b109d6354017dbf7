"""Temporal smoothness and the static prior on time planes [F, T, R] (time along dim -2)."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch

from dyngs.losses.temporal import time_l1_to_static, time_smoothness


def _in_time(values: torch.Tensor, f: int = 3, r: int = 5) -> torch.Tensor:
    """A plane whose every (f, ·, r) column is `values` along time."""
    return values.double()[None, :, None].expand(f, -1, r).clone()


def test_linear_in_time_is_smooth() -> None:
    t = torch.arange(7)
    # Any offset per column; dyadic values keep the arithmetic exact.
    offsets = torch.randint(-8, 8, (3, 1, 5), generator=torch.Generator().manual_seed(0)) / 4
    plane = _in_time(0.5 * t + 2) + offsets
    assert time_smoothness([plane]).item() == 0.0


def test_quadratic_in_time_costs_its_constant_second_difference() -> None:
    c = 0.25
    t = torch.arange(6)
    # Second difference of c·t² is 2c everywhere → squared (2c)² = 0.25.
    assert time_smoothness([_in_time(c * t * t)]).item() == pytest.approx((2 * c) ** 2)


def test_smoothness_is_along_dim_minus_two_only() -> None:
    # Quadratic along the spatial axis (dim -1), constant in time: no cost.
    r = torch.arange(6).double()
    plane = (r * r)[None, None, :].expand(2, 5, 6).clone()
    assert time_smoothness([plane]).item() == 0.0


def test_smoothness_mean_over_planes_and_short_planes() -> None:
    quadratic = _in_time(torch.arange(5) ** 2)  # second difference 2 → 4
    short = torch.rand(3, 2, 5)  # two time cells: no second difference
    assert time_smoothness([quadratic, _in_time(torch.arange(5))]).item() == pytest.approx(2.0)
    assert time_smoothness([short]).item() == 0.0


def test_static_prior() -> None:
    assert time_l1_to_static([torch.ones(4, 6, 8)]).item() == 0.0
    assert time_l1_to_static([torch.zeros(4, 6, 8)]).item() == 1.0
    planes = [torch.full((2, 3, 3), 0.5), torch.full((2, 3, 3), 3.0)]
    assert time_l1_to_static(planes).item() == pytest.approx((0.5 + 2.0) / 2)


def test_empty_lists() -> None:
    for loss in (time_smoothness, time_l1_to_static):
        value = loss([])
        assert isinstance(value, torch.Tensor) and value.shape == () and value.item() == 0.0


@pytest.mark.parametrize("loss", [time_smoothness, time_l1_to_static])
def test_gradient_reaches_every_plane(loss: Callable[[list[torch.Tensor]], torch.Tensor]) -> None:
    gen = torch.Generator().manual_seed(0)
    planes = [torch.rand(4, 9, 8, generator=gen).requires_grad_() for _ in range(3)]
    loss(planes).backward()
    for p in planes:
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0

"""Total variation of spatial planes on ramps with known answers."""

from __future__ import annotations

import pytest
import torch

from dyngs.losses.tv import plane_roughness, plane_tv


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


# Roughness: the TV over each channel's variance, so it measures shape, not size.


def test_roughness_of_a_ramp_is_its_step_over_its_variance() -> None:
    # a·j on 4×5 cells: steps of a along R0 only; the 20 values a·{0..4}, four times
    # each, have sample variance a²·(4·10)/19 (Σ(j−2)² = 10 per row).
    plane = _ramp(3.0, 0.0)
    expected = 9.0 / (9.0 * 40 / 19)
    assert plane_roughness([plane], eps=0.0).item() == pytest.approx(expected, rel=1e-12)


def test_roughness_does_not_change_with_scale() -> None:
    gen = torch.Generator().manual_seed(1)
    plane = torch.rand(3, 9, 7, generator=gen, dtype=torch.float64)
    base = plane_roughness([plane], eps=0.0)
    for factor in (1e-3, 0.5, 40.0):
        assert plane_roughness([plane * factor], eps=0.0).item() == pytest.approx(base.item())
    assert plane_roughness([plane + 5.0], eps=0.0).item() == pytest.approx(base.item())


def test_roughness_ranks_noise_above_a_smooth_wave() -> None:
    gen = torch.Generator().manual_seed(2)
    noise = torch.randn(8, 64, 64, generator=gen, dtype=torch.float64)
    assert plane_roughness([noise]).item() == pytest.approx(4.0, rel=0.03)
    r = 32
    j = torch.arange(r, dtype=torch.float64)
    wave = torch.sin(2 * torch.pi * j / r).expand(2, 5, r).clone()
    # one period along 32 cells: about (2π/32)², three hundred times smoother than noise
    assert plane_roughness([wave]).item() == pytest.approx((2 * torch.pi / r) ** 2, rel=0.1)


def test_roughness_of_constant_and_single_cell_planes_is_zero() -> None:
    assert plane_roughness([torch.full((2, 4, 3), 0.3)]).item() == 0.0
    assert plane_roughness([torch.ones(4, 1, 1)]).item() == 0.0
    value = plane_roughness([])
    assert value.shape == () and value.item() == 0.0


def test_roughness_descent_smooths_without_shrinking() -> None:
    # Fifty normalised gradient steps on a noisy plane: both losses make it smoother, the
    # roughness keeps its spread, the TV shrinks it towards a constant (the collapse the
    # roughness exists to avoid).
    gen = torch.Generator().manual_seed(3)
    start = torch.rand(1, 16, 16, generator=gen, dtype=torch.float64)
    spreads = {}
    for name, loss in (("roughness", plane_roughness), ("tv", plane_tv)):
        plane = start.clone().requires_grad_()
        for _ in range(50):
            plane.grad = None
            loss([plane]).backward()
            assert plane.grad is not None
            with torch.no_grad():
                plane -= 0.01 * plane.grad / plane.grad.abs().max()
        assert plane_roughness([plane]).item() < 0.5 * plane_roughness([start]).item()
        spreads[name] = plane.var().item() / start.var().item()
    assert spreads["roughness"] == pytest.approx(1.0, rel=0.05)
    assert spreads["tv"] < 0.5

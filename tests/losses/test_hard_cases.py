"""Hard cases for the losses (issue 5, docs/NUMERICS.md): SSIM on constant images and
ARAP with coincident neighbours, each with a value checked against its closed form and
finite gradients.

Letters: H×W image, N points, K neighbours.
"""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from dyngs.losses.arap import SAFE_NORM_EPS, arap_loss, neighbor_weights
from dyngs.losses.photometric import dssim, photometric, ssim_map
from dyngs.neighbors import knn

C1 = 0.01**2  # SSIM's stabilisers for data range 1 (Wang et al. 2004)
DTYPES = [pytest.param(torch.float32, id="float32"), pytest.param(torch.float64, id="float64")]


def _luminance(a: float, b: float) -> float:
    """SSIM of two constant images: the variances and covariance are 0, so the contrast-
    structure factor is c2 / c2 = 1 and only the luminance term (2ab + c1)/(a² + b² + c1)
    is left."""
    return (2 * a * b + C1) / (a * a + b * b + C1)


# float32 computes each variance as E[x²] − E[x]² over an 11×11 window, which for a
# constant image leaves a rounding residue of a few 1e-8; divided by c2 = 9e-4 that moves
# SSIM and its gradient by up to ~1e-4 (measured: 4e-5 and 6e-5).
SSIM_TOLERANCE = {torch.float32: 2e-4, torch.float64: 1e-12}


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("size", [(1, 1), (13, 17), (64, 64)])
@pytest.mark.parametrize(("a", "b"), [(0.0, 0.0), (1.0, 1.0), (0.0, 1.0), (0.3, 0.8), (0.5, 0.5)])
def test_ssim_on_constant_images(
    dtype: torch.dtype, size: tuple[int, int], a: float, b: float
) -> None:
    pred = torch.full((*size, 3), a, dtype=dtype, requires_grad=True)
    target = torch.full((*size, 3), b, dtype=dtype)
    ssim = ssim_map(pred, target)
    assert bool(torch.isfinite(ssim).all())
    assert float((ssim.detach().double() - _luminance(a, b)).abs().max()) <= SSIM_TOLERANCE[dtype]
    loss = dssim(pred, target)
    loss.backward()
    assert pred.grad is not None and bool(torch.isfinite(pred.grad).all())
    if a == b:  # SSIM is at its maximum, 1: the gradient vanishes
        assert float(pred.grad.abs().max()) <= SSIM_TOLERANCE[dtype]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("value", [0.0, 1.0])
def test_photometric_loss_of_a_constant_image_against_a_textured_one(
    dtype: torch.dtype, value: float
) -> None:
    # Black or white against noise: one side has zero variance, the other does not.
    gen = torch.Generator().manual_seed(0)
    target = torch.rand(24, 20, 3, generator=gen, dtype=torch.float64).to(dtype)
    pred = torch.full((24, 20, 3), value, dtype=dtype, requires_grad=True)
    loss = photometric(pred, target)
    assert bool(torch.isfinite(loss)) and 0 <= loss.item() <= 2
    loss.backward()
    assert pred.grad is not None and bool(torch.isfinite(pred.grad).all())


def _pairs(dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """Four points: 0 and 1 coincide, 2 and 3 coincide, the pairs 3 units apart."""
    base = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    neighbors = torch.tensor([[1], [0], [3], [2]])
    return base.to(dtype), neighbors


@pytest.mark.parametrize("dtype", DTYPES)
def test_arap_neighbours_coincident_at_one_time(dtype: torch.dtype) -> None:
    # At time a each point sits on its neighbour; at time b the twins are 0.5 apart. With
    # lengths √(d² + ε) the change is √(0.25 + ε) − √ε for every pair.
    pos_a, neighbors = _pairs(dtype)
    pos_a = pos_a.clone().requires_grad_(True)
    offset = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.5, 0.0]])
    pos_b = (pos_a.detach() + offset.to(dtype)).requires_grad_(True)
    weights = neighbor_weights(pos_a.detach(), neighbors, scale=1.0)
    assert bool((weights == 1).all())  # coincident: exp(0)
    loss = arap_loss(pos_a, pos_b, neighbors, weights)
    expected = math.sqrt(0.25 + SAFE_NORM_EPS) - math.sqrt(SAFE_NORM_EPS)
    tol = 1e-12 if dtype == torch.float64 else 1e-6
    assert loss.item() == pytest.approx(expected, abs=tol)
    loss.backward()
    for pos in (pos_a, pos_b):
        assert pos.grad is not None and bool(torch.isfinite(pos.grad).all())
    # At the coincident time the direction of a zero vector is undefined: safe_norm gives
    # it no gradient rather than NaN.
    assert pos_a.grad is not None and bool((pos_a.grad == 0).all())


@pytest.mark.parametrize("dtype", DTYPES)
def test_arap_neighbours_coincident_at_both_times(dtype: torch.dtype) -> None:
    pos_a, neighbors = _pairs(dtype)
    pos_a = pos_a.clone().requires_grad_(True)
    pos_b = (pos_a.detach() + 7.0).requires_grad_(True)  # moved rigidly, still coincident
    loss = arap_loss(pos_a, pos_b, neighbors, torch.ones(4, 1, dtype=dtype))
    assert loss.item() == 0.0
    loss.backward()
    for pos in (pos_a, pos_b):
        assert pos.grad is not None and bool((pos.grad == 0).all())


@pytest.mark.parametrize("dtype", DTYPES)
def test_arap_every_point_in_one_place(dtype: torch.dtype) -> None:
    # Twenty copies of one point (a Gaussian cloned over and over): knn still returns k
    # distinct other points, the weights are 1, and the loss is the change of √ε to the
    # spread-out lengths.
    pos_a = torch.full((20, 3), 2.5, dtype=dtype, requires_grad=True)
    neighbors = knn(pos_a.detach(), 4)
    assert neighbors.shape == (20, 4)
    assert bool((neighbors != torch.arange(20)[:, None]).all())
    weights = neighbor_weights(pos_a.detach(), neighbors, scale=0.1)
    assert bool((weights == 1).all())
    spread = torch.randn(20, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    pos_b = (pos_a.detach() + spread.to(dtype)).requires_grad_(True)
    loss = arap_loss(pos_a, pos_b, neighbors, weights)
    lengths = (spread[:, None, :] - spread[neighbors]).square().sum(-1) + SAFE_NORM_EPS
    expected = float((lengths.sqrt() - math.sqrt(SAFE_NORM_EPS)).abs().mean())
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert loss.item() == pytest.approx(expected, abs=tol)
    loss.backward()
    for pos in (pos_a, pos_b):
        assert pos.grad is not None and bool(torch.isfinite(pos.grad).all())

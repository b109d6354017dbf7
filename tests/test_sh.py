"""Spherical harmonics: the degree-0 shortcut is the general formula, to the bit."""

from __future__ import annotations

import pytest
import torch

from dyngs.sh import SH_C0, eval_sh, eval_sh0, sh_basis


def general_degree_0(coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """`eval_sh`'s general formula at degree 0, written out: basis times coefficients,
    summed over the one coefficient, plus 0.5, clamped at 0."""
    unit = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return ((sh_basis(0, unit)[..., None] * coeffs[:, :1]).sum(dim=-2) + 0.5).clamp_min(0.0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_degree_0_gives_the_general_formulas_values_and_gradients(dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(0)
    coeffs = 3 * torch.randn(500, 16, 3, generator=g, dtype=dtype)
    coeffs[:4, 0] = -0.5 / SH_C0  # exactly at the clamp: the gradient passes (≥ 0)
    dirs = torch.randn(500, 3, generator=g, dtype=dtype)
    dirs[0] = 0.0  # a zero direction changes nothing at degree 0
    upstream = torch.randn(500, 3, generator=g, dtype=dtype)
    results = []
    for colour in (general_degree_0, lambda c, _d: eval_sh0(c), lambda c, d: eval_sh(0, c, d)):
        c = coeffs.clone().requires_grad_()
        rgb = colour(c, dirs)
        rgb.backward(upstream)
        assert c.grad is not None
        results.append((rgb.detach(), c.grad))
    (want, want_grad), *others = results
    assert bool((want == 0).any()) and bool((want > 0).any())  # both sides of the clamp
    for rgb, grad in others:
        assert torch.equal(rgb, want)
        assert torch.equal(grad, want_grad)


def test_degree_0_reads_only_the_first_coefficient() -> None:
    coeffs = torch.zeros(2, 4, 3)
    coeffs[:, 1:] = torch.nan  # the degree-1 band, unread at degree 0
    coeffs[1, 0] = torch.tensor([1.0, -1.0, 0.0]) / SH_C0
    assert torch.equal(eval_sh0(coeffs), torch.tensor([[0.5, 0.5, 0.5], [1.5, 0.0, 0.5]]))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_the_model_draws_its_degrees_bands_and_the_rest_get_zero_gradients(degree: int) -> None:
    # `DynamicGaussians.at` joins only the bands a degree draws; the coefficients above get
    # a zero gradient, as when all sixteen were joined and sliced (Adam reads that tensor).
    from dyngs.fields import DeformationHeadConfig, HexPlaneConfig
    from dyngs.model import DynamicGaussians, GaussianConfig
    from dyngs.types import SceneBox

    gen = torch.Generator().manual_seed(degree)
    box = SceneBox((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    model = DynamicGaussians.build(GaussianConfig(), HexPlaneConfig(resolution=(4, 4, 4, 3)),
                                   DeformationHeadConfig(), box, 50, gen)  # fmt: skip
    with torch.no_grad():
        model.canonical.sh_rest.normal_(generator=gen)
    drawn = model.at(0.5, sh_degree=degree, deform=False)
    bands = (degree + 1) ** 2
    whole = torch.cat((model.canonical.sh_dc, model.canonical.sh_rest), dim=1)
    assert torch.equal(drawn.colors, whole[:, :bands])
    drawn.colors.square().sum().backward()
    grad = model.canonical.sh_rest.grad
    assert grad is not None and grad.shape == model.canonical.sh_rest.shape
    assert torch.equal(grad[:, bands - 1 :], torch.zeros_like(grad[:, bands - 1 :]))
    assert torch.equal(grad[:, : bands - 1], 2 * whole[:, 1:bands].detach())

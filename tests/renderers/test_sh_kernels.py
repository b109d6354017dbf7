"""`cpu-tile`'s compiled colours (`_Colors`, `sh_kernels`) held to `sh.eval_sh`, the
specification, as `project_compiled` calls it: values and both gradients at every
degree, zero and tiny directions, the clamp, gradcheck, and any thread count."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import Tensor

from dyngs.renderers.base import Guards
from dyngs.renderers.cpu_tile import _Colors, project_compiled
from dyngs.renderers.stages import project
from dyngs.sh import eval_sh
from tests.renderers.scenes import random_scene

pytest.importorskip("numba")


def _scene(n: int, degree: int, dtype: torch.dtype, seed: int = 0) -> tuple[Tensor, Tensor, Tensor]:
    """Coefficients, means and a camera centre away from the origin; some colours clamp."""
    g = torch.Generator().manual_seed(seed)
    coeffs = torch.randn(n, (degree + 1) ** 2, 3, generator=g, dtype=dtype)
    coeffs[::5, 0] -= 2.0  # below zero before the clamp
    center = torch.tensor([0.3, -1.2, 4.0], dtype=torch.float64)
    means = (torch.randn(n, 3, generator=g, dtype=torch.float64) * 2 + center).to(dtype)
    means[0] = center.to(dtype)  # seen from the camera centre: a zero direction
    means[1] = (center + 1e-14).to(dtype) if dtype == torch.float64 else means[1]
    return coeffs, means, center


def _reference(coeffs: Tensor, means: Tensor, center: Tensor, degree: int) -> Tensor:
    """As `project_compiled` called `eval_sh` before the colours were compiled."""
    return eval_sh(degree, coeffs, (means.to(torch.float64) - center).to(means.dtype))


def _both(coeffs: Tensor, means: Tensor, center: Tensor, degree: int, threads: int = 2):  # type: ignore[no-untyped-def]
    """Values and gradients, compiled and reference, under one weighted loss."""
    results = []
    for compiled in (True, False):
        c, m = coeffs.clone().requires_grad_(), means.clone().requires_grad_()
        if compiled:
            rgb = _Colors.apply(c, m, center.numpy(), degree, threads)
        else:
            rgb = _reference(c, m, center, degree)
        weights = torch.linspace(-1.0, 2.0, rgb.numel(), dtype=rgb.dtype).view_as(rgb)
        (rgb * weights).sum().backward()
        results.append((rgb.detach(), c.grad, m.grad))
    return results


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("degree", [1, 2, 3])
def test_colours_and_gradients_match_eval_sh(degree: int, dtype: torch.dtype) -> None:
    coeffs, means, center = _scene(300, degree, dtype)
    (rgb, coeffs_grad, means_grad), (want, want_coeffs, want_means) = _both(
        coeffs, means, center, degree
    )
    assert bool((want == 0).any()) and bool((want > 0).any())  # both sides of the clamp
    value_tolerance = 1e-9 if dtype == torch.float64 else 1e-5
    assert float((rgb - want).abs().max()) <= value_tolerance
    relative = 1e-9 if dtype == torch.float64 else 1e-4
    for got, expected in ((coeffs_grad, want_coeffs), (means_grad, want_means)):
        assert got is not None and expected is not None
        assert got.dtype == expected.dtype and got.shape == expected.shape
        # The zero direction's gradient is the floor's 1e12 times the pull, in both:
        # compared on its own scale, the others on theirs.
        for rows in (slice(0, 1), slice(1, None)):
            scale = float(expected[rows].abs().max())
            diff = float((got[rows] - expected[rows]).abs().max())
            assert diff <= relative * max(scale, 1e-30), f"{diff:.3g} of {scale:.3g}"


def test_gradcheck_in_float64() -> None:
    coeffs, means, center = _scene(6, 3, torch.float64, seed=1)
    # Away from the centre: finite differences must not step across the norm's floor.
    means[:2] = center + torch.tensor([0.5, 0.3, -0.2], dtype=torch.float64)
    coeffs.requires_grad_()
    means.requires_grad_()
    assert torch.autograd.gradcheck(
        lambda c, m: _Colors.apply(c, m, center.numpy(), 3, 2), (coeffs, means)
    )


def test_means_without_gradient_get_none_and_coefficients_still_do() -> None:
    coeffs, means, center = _scene(40, 2, torch.float32)
    c = coeffs.clone().requires_grad_()
    rgb = _Colors.apply(c, means, center.numpy(), 2, 2)
    rgb.sum().backward()
    assert c.grad is not None and means.grad is None


def test_the_same_colours_and_gradients_at_every_thread_count() -> None:
    coeffs, means, center = _scene(1000, 3, torch.float32, seed=2)  # several jobs
    one, two = (_both(coeffs, means, center, 3, threads)[0] for threads in (1, 2))
    for a, b in zip(one, two, strict=True):
        assert torch.equal(a, b)


def test_a_render_at_degree_3_matches_the_reference_renderer() -> None:
    """Through the whole renderer: `project_compiled`'s colours against `stages.project`'s."""
    gaussians, camera, _ = random_scene(3, 200, 40, 30, sh_degree=3)
    got = project_compiled(gaussians, camera, Guards()).colors
    want = project(gaussians, camera, Guards()).colors
    assert np.allclose(got.numpy(), want.numpy(), rtol=0, atol=1e-9)

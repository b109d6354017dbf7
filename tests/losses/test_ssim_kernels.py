"""SSIM from its moments, compiled (dyngs/losses/ssim_kernels.py), held to
`photometric.ssim_from_moments` in PyTorch: values and gradients in float64 and float32,
on random images, flat ones (variances zero or rounded below it) and the extremes."""

from __future__ import annotations

import importlib

import pytest
import torch
from kornia.filters import get_gaussian_kernel1d

# `dyngs.losses.photometric` is also the name of a function the package exports.
photometric = importlib.import_module("dyngs.losses.photometric")


def _moments(kind: str, dtype: torch.dtype, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """μx, ⟨x²⟩, ⟨xy⟩, μy, ⟨y²⟩ of a [1, 3, 24, 20] pair blurred as SSIM blurs them."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(1, 3, 24, 20, generator=gen, dtype=torch.float64)
    y = torch.rand(1, 3, 24, 20, generator=gen, dtype=torch.float64)
    if kind == "flat":  # variances of exactly 0, or a rounding below it
        x, y = torch.full_like(x, 0.3), torch.full_like(y, 0.7)
    elif kind == "extremes":  # black, white and identical pixels side by side
        x[..., :8], y[..., :8] = 0.0, 0.0
        x[..., 8:12], y[..., 8:12] = 1.0, 0.0
        y[..., 12:] = x[..., 12:]
    x, y = x.to(dtype), y.to(dtype)
    taps = get_gaussian_kernel1d(11, 1.5, dtype=dtype)
    blurred = photometric.gaussian_blur(torch.cat((x, x * x, x * y, y, y * y), 1), taps)
    return tuple(m.contiguous() for m in blurred.split(3, dim=1))


def _map_and_grads(moments: tuple[torch.Tensor, ...], compiled: bool, upstream: torch.Tensor):
    leaves = [m.detach().clone().requires_grad_(i < 3) for i, m in enumerate(moments)]
    if compiled:
        ssim = photometric._CompiledSsim.apply(*leaves)
    else:
        ssim = photometric.ssim_from_moments(*leaves)
    ssim.backward(upstream.to(ssim.dtype))
    return ssim.detach(), [leaf.grad for leaf in leaves[:3]]


@pytest.mark.parametrize("kind", ["random", "flat", "extremes"])
def test_the_compiled_map_and_gradients_are_the_reference(kind: str) -> None:
    upstream = torch.randn(1, 3, 24, 20, generator=torch.Generator().manual_seed(1)).double()
    moments = _moments(kind, torch.float64)
    truth, truth_grads = _map_and_grads(moments, False, upstream)
    ours, ours_grads = _map_and_grads(moments, True, upstream)
    assert float((ours - truth).abs().max()) <= 1e-12
    for mine, reference in zip(ours_grads, truth_grads, strict=True):
        assert mine is not None and reference is not None
        scale = max(float(reference.abs().max()), 1.0)
        assert float((mine - reference).abs().max()) <= 1e-10 * scale
    # float32 moments: every pixel computed in float64 and rounded once, so within a
    # rounding or two of the float64 reference of the same (float32) moments.
    moments32 = tuple(m.float() for m in moments)
    truth32, truth32_grads = _map_and_grads(tuple(m.double() for m in moments32), False, upstream)
    ours32, ours32_grads = _map_and_grads(moments32, True, upstream)
    assert ours32.dtype == torch.float32
    assert float((ours32.double() - truth32).abs().max()) <= 2e-7
    for mine, reference in zip(ours32_grads, truth32_grads, strict=True):
        assert mine is not None and reference is not None and mine.dtype == torch.float32
        scale = float(reference.abs().max())
        assert float((mine.double() - reference).abs().max()) <= 1e-6 * scale


def test_gradcheck() -> None:
    moments = _moments("random", torch.float64)
    small = [m[..., 5:9, 3:6].contiguous() for m in moments]
    leaves = [m.requires_grad_(i < 3) for i, m in enumerate(small)]
    assert torch.autograd.gradcheck(photometric._CompiledSsim.apply, leaves)


def test_thread_counts_give_the_same_bits() -> None:
    upstream = torch.randn(1, 3, 24, 20, generator=torch.Generator().manual_seed(2))
    moments = _moments("random", torch.float32)
    results = []
    for threads in (1, 2):  # within numba's pool: `compiled.thread_count`
        before = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            results.append(_map_and_grads(moments, True, upstream))
        finally:
            torch.set_num_threads(before)
    (map_a, grads_a), (map_b, grads_b) = results
    assert torch.equal(map_a, map_b)
    assert all(torch.equal(a, b) for a, b in zip(grads_a, grads_b, strict=True))


def test_a_target_that_needs_a_gradient_gets_it_from_the_reference() -> None:
    gen = torch.Generator().manual_seed(3)
    pred = torch.rand(16, 16, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    target = torch.rand(16, 16, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    photometric.ssim_map(pred, target).sum().backward()
    assert target.grad is not None and pred.grad is not None
    # SSIM is symmetric in its two images, so each gets the gradient the other would.
    swapped_pred = target.detach().clone().requires_grad_()
    photometric.ssim_map(swapped_pred, pred.detach()).sum().backward()
    assert swapped_pred.grad is not None
    assert torch.allclose(swapped_pred.grad, target.grad, rtol=0, atol=1e-12)

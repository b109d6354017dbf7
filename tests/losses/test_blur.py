"""SSIM's compiled blur (dyngs/losses/blur_kernels.py) held to kornia's separable filter,
its adjoint to autograd's, in float64 and float32, at sizes down to the window's edge."""

from __future__ import annotations

import numba
import numpy as np
import pytest
import torch
from kornia.filters import filter2d_separable, get_gaussian_kernel1d

from dyngs.losses import blur_kernels
from dyngs.losses.photometric import _CompiledBlur, gaussian_blur

SIZES = [(15, 64, 48, 11), (3, 17, 30, 11), (2, 9, 9, 7), (1, 3, 5, 5), (4, 6, 6, 11)]
"""(channels, height, width, taps): the last has r = 5 < 6, the smallest reflect allows."""


def _case(channels: int, height: int, width: int, taps: int, dtype: torch.dtype, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    images = torch.rand(1, channels, height, width, generator=gen, dtype=dtype)
    grad = torch.rand(1, channels, height, width, generator=gen, dtype=dtype)
    kernel = get_gaussian_kernel1d(taps, 1.5, dtype=torch.float64)
    return images, grad, kernel


def _kornia(images: torch.Tensor, grad: torch.Tensor, kernel: torch.Tensor):
    """kornia's blur in float64 of the same inputs, and the adjoint applied to grad."""
    leaf = images.detach().double().requires_grad_(True)
    out = filter2d_separable(leaf, kernel, kernel)
    out.backward(grad.double())
    assert leaf.grad is not None
    return out.detach(), leaf.grad


def _compiled(images: torch.Tensor, grad: torch.Tensor, kernel: torch.Tensor):
    out = np.empty_like(images[0].numpy())
    blur_kernels.blur(images[0].numpy(), kernel.reshape(-1).numpy(), out)
    back = np.empty_like(out)
    blur_kernels.blur_adjoint(grad[0].numpy(), kernel.reshape(-1).numpy(), back)
    return torch.from_numpy(out)[None], torch.from_numpy(back)[None]


@pytest.mark.parametrize(("channels", "height", "width", "taps"), SIZES)
def test_float64_is_kornias(channels: int, height: int, width: int, taps: int) -> None:
    images, grad, kernel = _case(channels, height, width, taps, torch.float64)
    want, want_grad = _kornia(images, grad, kernel)
    got, got_grad = _compiled(images, grad, kernel)
    assert float((got - want).abs().max()) <= 1e-15
    assert float((got_grad - want_grad).abs().max()) <= 1e-14 * float(want_grad.abs().max())


@pytest.mark.parametrize(("channels", "height", "width", "taps"), SIZES)
def test_float32_is_the_exact_blur_rounded_once(
    channels: int, height: int, width: int, taps: int
) -> None:
    # Sums in float64, one rounding: within half an ulp of the float64 result (2⁻²⁴ of its
    # magnitude), where kornia's float32 convolution rounds at every step.
    images, grad, kernel = _case(channels, height, width, taps, torch.float32)
    want, want_grad = _kornia(images, grad, kernel)
    got, got_grad = _compiled(images, grad, kernel)
    assert got.dtype == got_grad.dtype == torch.float32
    for value, exact in ((got, want), (got_grad, want_grad)):
        ulp = 2.0**-24 * exact.abs().clamp_min(2.0**-126)
        assert bool(((value.double() - exact).abs() <= ulp).all())


def test_the_autograd_function_passes_gradcheck() -> None:
    images, _, kernel = _case(2, 7, 8, 5, torch.float64)
    leaf = images.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: _CompiledBlur.apply(x, kernel[None]), (leaf,))


def test_same_at_any_thread_count_and_run() -> None:
    images, grad, kernel = _case(15, 40, 33, 11, torch.float32)
    results = []
    for threads in (1, 2, 1):
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]
        results.append(_compiled(images, grad, kernel))
    for out, back in results[1:]:
        assert torch.equal(out, results[0][0]) and torch.equal(back, results[0][1])


def test_gaussian_blur_uses_the_compiled_kernels_on_a_cpu() -> None:
    images, _, kernel = _case(3, 12, 12, 11, torch.float32)
    leaf = images.requires_grad_(True)
    out = gaussian_blur(leaf, kernel[None].float())
    assert out.grad_fn is not None and "CompiledBlur" in type(out.grad_fn).__name__

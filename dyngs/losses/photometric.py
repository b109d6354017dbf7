"""Photometric losses: L1, D-SSIM and their blend (Kerbl et al. 2023).

Letters: H×W image, C channels (3 for RGB). Images are float HWC in [0, 1]; a mask is
[H, W, 1] (or [H, W]), bool or float, and turns every mean into a mean over the masked
pixels (a soft mask weights them).

Which SSIM. `ssim_map` is `kornia.metrics.ssim`: a Gaussian window (σ = 1.5 whatever its
size), c1 = (0.01)², c2 = (0.03)² for data range 1, with kornia's `eps` set to 0 so that
SSIM(x, x) is exactly 1 even for flat images (its default 1e-12 makes two black images
score 0.99998889). It is computed as kornia computes it, with kornia's window and
separable filter, but the five local moments (x, y, x², y², xy) go through two filter
calls (the prediction's three, then the target's two, which need no backward pass) instead
of five, which is faster on small images (docs/TRAINING.md measures it). On a CPU the
filter is compiled (`gaussian_blur`), and so is the map from the moments
(`ssim_kernels`, whose PyTorch reference is `ssim_from_moments`);
tests/losses/test_photometric.py holds the whole to kornia's own function. The loss uses
D-SSIM = 1 − SSIM, as 3D Gaussian Splatting does, so that its
λ = 0.2 carries over; `kornia.losses.ssim_loss` is (1 − SSIM) / 2, clamped, which
would silently halve the weight. The training map is 'same' size with reflect padding;
the evaluation metric (`dyngs.metrics.ssim`) uses the 'valid' map instead.

Images smaller than the window. kornia's reflect padding needs H and W larger than half
the window, and a 'valid' map needs H and W at least the window. Rather than crash, the
window shrinks to the largest odd size that fits (down to 1 for a 1×1 image, where SSIM
reduces to its luminance term, finite for any pair of constants because c1 > 0).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any, Literal

import numpy as np
import torch
from jaxtyping import Float
from kornia.filters import filter2d_separable, get_gaussian_kernel1d
from torch import Tensor

from dyngs.compiled import numba_available, run_kernel, thread_count

DSSIM_WEIGHT = 0.2
"""λ in (1 − λ)·L1 + λ·D-SSIM, as in 3D Gaussian Splatting (Kerbl et al. 2023)."""

SSIM_WINDOW = 11
"""Window size of standard SSIM (Wang et al. 2004): 11×11 Gaussian, σ = 1.5."""

C1, C2 = 0.01**2, 0.03**2
"""SSIM's stabilisers for data range 1 (Wang et al. 2004): (K1 L)², (K2 L)², K1 = 0.01,
K2 = 0.03."""

Padding = Literal["same", "valid"]


def _check_pair(pred: Tensor, target: Tensor) -> None:
    if pred.shape != target.shape or pred.ndim != 3:
        raise ValueError(
            f"images must both be [H, W, C], got {tuple(pred.shape)} and {tuple(target.shape)}"
        )


def _mask_weights(mask: Tensor, like: Tensor) -> Float[Tensor, "H W 1"]:
    """The mask as float weights [H, W, 1] in `like`'s dtype and device."""
    if mask.ndim == 2:
        mask = mask[..., None]
    if mask.shape != (*like.shape[:2], 1):
        raise ValueError(
            f"mask must be [H, W, 1] for images {tuple(like.shape)}, got {tuple(mask.shape)}"
        )
    return mask.to(device=like.device, dtype=like.dtype)


def _masked_mean(values: Float[Tensor, "H W C"], mask: Tensor | None) -> Float[Tensor, ""]:
    """Mean over all elements, or over the masked pixels (weights broadcast over C).

    An empty mask gives 0 (with a zero gradient), not 0/0.
    """
    if mask is None:
        return values.mean()
    weights = _mask_weights(mask, values)
    total = (values * weights).sum()
    count = weights.sum() * values.shape[-1]
    # count is 0 only for an empty mask, and then total is 0 too: 0 / tiny = 0.
    return total / count.clamp_min(torch.finfo(values.dtype).tiny)


def fit_window(window_size: int, height: int, width: int, padding: Padding = "same") -> int:
    """The largest odd window ≤ `window_size` that kornia's SSIM accepts for H×W.

    'same' reflects half a window into the image, so it needs window // 2 < min(H, W);
    'valid' needs window ≤ min(H, W).
    """
    if window_size < 1 or window_size % 2 == 0:
        raise ValueError(f"SSIM window size must be odd and positive, got {window_size}")
    side = min(height, width)
    largest = 2 * side - 1 if padding == "same" else side
    window = min(window_size, largest)
    return window if window % 2 == 1 else window - 1


def gaussian_blur(images: Float[Tensor, "1 C H W"], taps: Float[Tensor, "1 K"]) -> Tensor:
    """The separable blur of SSIM's window with reflect padding, 'same' size: kornia's
    `filter2d_separable`, or on a CPU with numba installed the compiled kernels of
    `dyngs.losses.blur_kernels` (3.5× faster forward and backward on SSIM's fifteen
    channels at 128², where PyTorch runs one small convolution per channel; float64 the
    same to the bit forward, float32 within its rounding: tests/losses/test_blur.py)."""
    if not _compiled_here(images):
        return filter2d_separable(images, taps, taps)
    return _CompiledBlur.apply(images, taps)


class _CompiledBlur(torch.autograd.Function):
    """`gaussian_blur` by `blur_kernels`, with its adjoint as the backward (the taps get
    no gradient: SSIM's window is fixed)."""

    @staticmethod
    def forward(ctx: Any, images: Tensor, taps: Tensor) -> Tensor:  # type: ignore[override]
        from dyngs.losses import blur_kernels

        weights = taps.detach().reshape(-1).to(torch.float64).numpy()
        ctx.weights = weights
        source = images.detach()[0].contiguous().numpy()
        out = np.empty_like(source)
        run_kernel(blur_kernels.blur, thread_count(None), str(source.dtype), source, weights,
                   out)  # fmt: skip
        return torch.from_numpy(out)[None]

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        from dyngs.losses import blur_kernels

        upstream = grad.detach()[0].contiguous().numpy()
        out = np.empty_like(upstream)
        run_kernel(blur_kernels.blur_adjoint, thread_count(None), str(upstream.dtype),
                   upstream, ctx.weights, out)  # fmt: skip
        return torch.from_numpy(out)[None], None


def ssim_map(
    pred: Float[Tensor, "H W C"],
    target: Float[Tensor, "H W C"],
    window_size: int = SSIM_WINDOW,
    padding: Padding = "same",
) -> Float[Tensor, "h w C"]:
    """Per-pixel, per-channel SSIM (kornia's, Gaussian σ = 1.5, data range 1, eps 0).

    'same' keeps H×W; 'valid' drops half a window on every side (h = H − window + 1).
    The window shrinks to fit small images (see the module docstring).
    """
    _check_pair(pred, target)
    window = fit_window(window_size, pred.shape[0], pred.shape[1], padding)
    dtype = torch.promote_types(pred.dtype, target.dtype)
    a, b = pred.to(dtype).permute(2, 0, 1)[None], target.to(dtype).permute(2, 0, 1)[None]
    kernel = ssim_taps(window, a.device, dtype)
    # 'same': reflect padding; 'valid' is the 'same' map cropped, as kornia computes it.
    # The target's moments are blurred apart from the prediction's: the blur treats every
    # channel alone (the same values), and a target that needs no gradient then costs no
    # adjoint pass (6 of 15 channels for RGB).
    channels = a.shape[1]
    predicted = _blurred(torch.cat((a, a * a, a * b), 1), kernel, window, padding)
    mu1, mean11, mean12 = predicted.split(channels, dim=1)
    mu2, mean22 = _blurred(torch.cat((b, b * b), 1), kernel, window, padding).split(channels, 1)
    if _compiled_here(mu1) and not (mu2.requires_grad or mean22.requires_grad):
        ssim = _CompiledSsim.apply(mu1, mean11, mean12, mu2, mean22)
    else:
        ssim = ssim_from_moments(mu1, mean11, mean12, mu2, mean22)
    return ssim[0].permute(1, 2, 0)


@lru_cache(maxsize=16)
def ssim_taps(window: int, device: torch.device, dtype: torch.dtype) -> Float[Tensor, "1 K"]:
    """SSIM's Gaussian window (σ = 1.5), kornia's, built once per size, device and dtype:
    kornia builds it from scratch, ~0.1 ms a call on the CPU, a constant paid by every
    training step. Read only: the blurs never write it."""
    return get_gaussian_kernel1d(window, 1.5, device=device, dtype=dtype)


def ssim_from_moments(
    mu1: Tensor, mean11: Tensor, mean12: Tensor, mu2: Tensor, mean22: Tensor
) -> Tensor:
    """SSIM from the blurred moments μx, ⟨x²⟩, ⟨xy⟩, μy, ⟨y²⟩ (x the prediction, y the
    target), as kornia computes it with eps 0: the specification that `ssim_kernels`
    is held to."""
    mu1_sq, mu2_sq, mu1_mu2 = mu1**2, mu2**2, mu1 * mu2
    num = (2.0 * mu1_mu2 + C1) * (2.0 * (mean12 - mu1_mu2) + C2)
    # No eps: c1 and c2 already keep the denominator ≥ c1·c2 > 0 (up to a rounding of the
    # variances that is far below c2 = 9e-4).
    den = (mu1_sq + mu2_sq + C1) * ((mean11 - mu1_sq) + (mean22 - mu2_sq) + C2)
    return num / den


class _CompiledSsim(torch.autograd.Function):
    """`ssim_from_moments` by `ssim_kernels`, one pass each way; the target's moments get
    no gradient (the caller takes this path only when they need none)."""

    @staticmethod
    def forward(ctx: Any, *moments: Tensor) -> Tensor:  # type: ignore[override]
        from dyngs.losses import ssim_kernels

        kept = tuple(m.detach().contiguous() for m in moments)
        out = torch.empty_like(kept[0])
        run_kernel(ssim_kernels.ssim_forward, thread_count(None), str(out.dtype),
                   *_flat(*kept), C1, C2, *_flat(out))  # fmt: skip
        ctx.save_for_backward(*kept)
        return out

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        from dyngs.losses import ssim_kernels

        kept = ctx.saved_tensors
        upstream = grad.to(kept[0].dtype).contiguous()
        grads = tuple(torch.empty_like(kept[0]) for _ in range(3))
        run_kernel(ssim_kernels.ssim_backward, thread_count(None), str(upstream.dtype),
                   *_flat(*kept), C1, C2, *_flat(upstream, *grads))  # fmt: skip
        return (*grads, None, None)


def _flat(*tensors: Tensor) -> tuple[np.ndarray, ...]:
    """Contiguous tensors' memory as flat NumPy arrays (no copy)."""
    return tuple(t.numpy().reshape(-1) for t in tensors)


def _compiled_here(tensor: Tensor) -> bool:
    """Whether the compiled kernels serve this tensor (a CPU one, numba installed)."""
    return tensor.device.type == "cpu" and numba_available()


def _blurred(
    channels: Float[Tensor, "1 M H W"], kernel: Tensor, window: int, padding: Padding
) -> Float[Tensor, "1 M h w"]:
    """`channels` blurred by SSIM's window, cropped by half a window for 'valid'."""
    moments = gaussian_blur(channels, kernel)
    if padding == "valid":
        half = window // 2
        moments = moments[..., half : moments.shape[-2] - half, half : moments.shape[-1] - half]
    return moments


def l1(
    pred: Float[Tensor, "H W C"],
    target: Float[Tensor, "H W C"],
    mask: Tensor | None = None,
) -> Float[Tensor, ""]:
    """Mean absolute error, over all pixels or over the masked ones."""
    _check_pair(pred, target)
    return _masked_mean((pred - target).abs(), mask)


def dssim(
    pred: Float[Tensor, "H W C"],
    target: Float[Tensor, "H W C"],
    window_size: int = SSIM_WINDOW,
    mask: Tensor | None = None,
) -> Float[Tensor, ""]:
    """D-SSIM = 1 − mean SSIM, in [0, 2]; with a mask the SSIM map is weighted by it.

    The masked version still filters across the mask edge (the window sees unmasked
    neighbours); only the averaging is restricted.
    """
    return _masked_mean(1.0 - ssim_map(pred, target, window_size), mask)


def photometric(
    pred: Float[Tensor, "H W C"],
    target: Float[Tensor, "H W C"],
    dssim_weight: float = DSSIM_WEIGHT,
    mask: Tensor | None = None,
) -> Float[Tensor, ""]:
    """(1 − λ)·L1 + λ·D-SSIM (Kerbl et al. 2023, λ = 0.2); a term of weight 0 is skipped."""
    if not 0.0 <= dssim_weight <= 1.0:
        raise ValueError(f"dssim_weight must lie in [0, 1], got {dssim_weight}")
    if dssim_weight == 0.0:
        return l1(pred, target, mask)
    if dssim_weight == 1.0:
        return dssim(pred, target, mask=mask)
    return (1.0 - dssim_weight) * l1(pred, target, mask) + dssim_weight * dssim(
        pred, target, mask=mask
    )

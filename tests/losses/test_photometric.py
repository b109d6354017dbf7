"""L1, D-SSIM and the photometric blend on tiny images with known answers."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
import torch
from kornia.filters import get_gaussian_kernel1d
from kornia.losses import ssim_loss
from kornia.metrics import ssim as kornia_ssim

from dyngs.losses.photometric import dssim, fit_window, l1, photometric, ssim_map, ssim_taps

C1 = 0.01**2  # SSIM's stabilisers for data range 1 (Wang et al. 2004)


def _luminance(a: float, b: float) -> float:
    """SSIM of two flat images: the contrast-structure term is c2 / c2 = 1."""
    return (2 * a * b + C1) / (a * a + b * b + C1)


def _rand(*shape: int, seed: int = 0) -> torch.Tensor:
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def test_l1_on_a_2x2_image() -> None:
    pred = torch.zeros(2, 2, 3)
    target = torch.tensor([[0.0, 0.1, 0.2], [0.3, 0.4, 0.5]]).repeat(2, 1).view(2, 2, 3)
    # Twelve values: 0, .1, ..., .5 twice → mean 0.25.
    assert l1(pred, target).item() == pytest.approx(0.25)


def test_l1_mask_averages_over_masked_pixels_only() -> None:
    pred = torch.zeros(2, 2, 3)
    target = torch.tensor([0.1, 0.2, 0.3, 0.4]).view(2, 2, 1).expand(2, 2, 3)
    mask = torch.tensor([[True, False], [False, True]]).view(2, 2, 1)
    assert l1(pred, target, mask).item() == pytest.approx((0.1 + 0.4) / 2)
    # A soft mask weights the pixels; an [H, W] mask is accepted too.
    soft = torch.tensor([[1.0, 0.0], [0.0, 0.5]])
    assert l1(pred, target, soft).item() == pytest.approx((0.1 + 0.5 * 0.4) / 1.5)
    # uint8 masks (0/1 or 0/255, as datamanagers store them) give the same mean.
    for high in (1, 255):
        as_uint8 = mask.to(torch.uint8) * high
        assert l1(pred, target, as_uint8).item() == pytest.approx((0.1 + 0.4) / 2)


def test_empty_mask_gives_zero_with_a_finite_gradient() -> None:
    pred = _rand(8, 8, 3).requires_grad_()
    loss = photometric(pred, _rand(8, 8, 3, seed=1), mask=torch.zeros(8, 8, 1))
    loss.backward()
    assert loss.item() == 0.0
    assert pred.grad is not None and torch.isfinite(pred.grad).all()


def test_mask_hides_changes_outside_it() -> None:
    pred, target = _rand(6, 6, 3), _rand(6, 6, 3, seed=1)
    mask = torch.zeros(6, 6, 1)
    mask[:3] = 1
    changed = pred.clone()
    changed[3:] = 1.0 - changed[3:]
    assert photometric(changed, target, 0.0, mask) == photometric(pred, target, 0.0, mask)
    assert l1(changed, target) != l1(pred, target)


def test_masked_dssim_weights_the_ssim_map() -> None:
    pred, target = _rand(12, 12, 3), _rand(12, 12, 3, seed=1)
    mask = (_rand(12, 12, 1, seed=2) > 0.5).double()
    expected = ((1 - ssim_map(pred, target)) * mask).sum() / (mask.sum() * 3)
    torch.testing.assert_close(dssim(pred, target, mask=mask), expected)


def test_dssim_of_an_image_with_itself_is_zero() -> None:
    x = _rand(16, 16, 3)
    torch.testing.assert_close(dssim(x, x), torch.zeros((), dtype=x.dtype), atol=1e-12, rtol=0)


def test_dssim_is_one_minus_ssim_not_kornias_half() -> None:
    pred, target = _rand(16, 16, 3), _rand(16, 16, 3, seed=1)
    a, b = pred.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]
    torch.testing.assert_close(dssim(pred, target), 2 * ssim_loss(a, b, 11, eps=0.0))


@pytest.mark.parametrize(("a", "b"), [(0.0, 0.0), (0.5, 0.5), (1.0, 1.0), (0.2, 0.7), (0.0, 1.0)])
@pytest.mark.parametrize("size", [(1, 1), (5, 7), (16, 16)])
def test_ssim_of_constant_images_is_the_luminance_term(
    a: float, b: float, size: tuple[int, int]
) -> None:
    pred = torch.full((*size, 3), a, dtype=torch.float64)
    target = torch.full((*size, 3), b, dtype=torch.float64)
    value = dssim(pred, target)
    assert torch.isfinite(value)
    assert value.item() == pytest.approx(1 - _luminance(a, b), abs=1e-9)


@pytest.mark.parametrize("size", [(1, 1), (1, 4), (2, 2), (3, 3), (5, 7), (7, 5), (11, 11)])
def test_tiny_images_are_finite_and_differentiable(size: tuple[int, int]) -> None:
    pred = _rand(*size, 3).requires_grad_()
    loss = photometric(pred, _rand(*size, 3, seed=1))
    loss.backward()
    assert torch.isfinite(loss)
    assert pred.grad is not None and torch.isfinite(pred.grad).all()
    assert ssim_map(pred, pred).shape == (*size, 3)


def test_the_window_shrinks_to_fit() -> None:
    assert fit_window(11, 64, 64) == 11
    assert fit_window(11, 5, 7) == 9  # reflect padding needs window // 2 < 5
    assert fit_window(11, 1, 1) == 1
    assert fit_window(11, 5, 7, padding="valid") == 5
    assert fit_window(11, 2, 9, padding="valid") == 1
    with pytest.raises(ValueError, match="odd"):
        fit_window(10, 64, 64)


def test_photometric_blend() -> None:
    pred, target = _rand(9, 10, 3), _rand(9, 10, 3, seed=1)
    torch.testing.assert_close(photometric(pred, target, 0.0), l1(pred, target))
    torch.testing.assert_close(photometric(pred, target, 1.0), dssim(pred, target))
    expected = 0.8 * l1(pred, target) + 0.2 * dssim(pred, target)
    torch.testing.assert_close(photometric(pred, target), expected)
    with pytest.raises(ValueError, match="dssim_weight"):
        photometric(pred, target, 1.5)


@pytest.mark.parametrize("weight", [0.0, 0.2, 1.0])
def test_gradients_reach_the_prediction(weight: float) -> None:
    pred = _rand(12, 12, 3).requires_grad_()
    photometric(pred, _rand(12, 12, 3, seed=1), weight).backward()
    assert pred.grad is not None
    assert torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0


def test_the_targets_moments_cost_no_adjoint_pass(monkeypatch: pytest.MonkeyPatch) -> None:
    # A training target needs no gradient, so SSIM's backward blurs back the prediction's
    # three moments (9 channels of RGB), not all five (15).
    pytest.importorskip("numba")
    module = importlib.import_module("dyngs.losses.photometric")  # the package's name is a function
    passes: list[tuple[str, int]] = []
    inner = module.run_kernel

    def recorded(kernel: object, count: int, signature: str, *args: np.ndarray) -> None:
        passes.append((getattr(kernel, "__name__", ""), args[0].shape[0]))
        inner(kernel, count, signature, *args)

    monkeypatch.setattr(module, "run_kernel", recorded)
    pred = _rand(20, 16, 3).requires_grad_()
    dssim(pred, _rand(20, 16, 3, seed=1)).backward()
    blurs = sorted(p for p in passes if p[0].startswith("blur"))
    assert blurs == [("blur", 6), ("blur", 9), ("blur_adjoint", 9)]


def test_shape_mismatch_is_an_error() -> None:
    with pytest.raises(ValueError, match="H, W, C"):
        l1(torch.zeros(2, 2, 3), torch.zeros(2, 3, 3))
    with pytest.raises(ValueError, match="mask"):
        l1(torch.zeros(2, 2, 3), torch.zeros(2, 2, 3), torch.ones(2, 2, 3))


def _map_and_grad(
    pred: torch.Tensor,
    target: torch.Tensor,
    window: int,
    padding: str,
    weights: torch.Tensor,
    kornia: bool,
) -> tuple[torch.Tensor, torch.Tensor]:
    """SSIM map (ours or kornia's `metrics.ssim`, eps 0) and the gradient of Σ map · weights
    with respect to pred."""
    leaf = pred.detach().clone().requires_grad_(True)
    if kornia:
        height, width = pred.shape[:2]
        fitted = fit_window(window, height, width, padding)  # type: ignore[arg-type]
        value = kornia_ssim(leaf.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], fitted,
                            max_val=1.0, eps=0.0, padding=padding)[0].permute(1, 2, 0)  # fmt: skip
    else:
        value = ssim_map(leaf, target, window, padding=padding)  # type: ignore[arg-type]
    (value * weights).sum().backward()
    assert leaf.grad is not None
    return value.detach(), leaf.grad


@pytest.mark.parametrize("padding", ["same", "valid"])
@pytest.mark.parametrize(
    ("height", "width", "window"), [(64, 48, 11), (17, 30, 11), (9, 9, 7), (3, 5, 11)]
)
def test_ssim_map_is_kornias(padding: str, height: int, width: int, window: int) -> None:
    # The map filters kornia's five moments in two calls (the prediction's three, the target's
    # two), compiled on a CPU; it must be kornia's `metrics.ssim` (eps 0), values and gradients,
    # for every padding and window fit. In float64 to 1e-13. In float32 the map's own arithmetic
    # rounds at ~1e-6, and a filter that sums in another order than kornia's convolution differs
    # from it by that much; so there both are held to the float64 map: ours within 2e-6
    # (kornia's own float32 map errs by up to 2.7e-6 on these cases, ours by up to 1.3e-6) and
    # its gradient within 1e-6 of the largest entry of the float64 one.
    gen = torch.Generator().manual_seed(height * width)
    pred = torch.rand(height, width, 3, generator=gen, dtype=torch.float64)
    target = torch.rand(height, width, 3, generator=gen, dtype=torch.float64)
    size = fit_window(window, height, width, padding)  # type: ignore[arg-type]
    crop = size - 1 if padding == "valid" else 0
    weights = torch.rand(height - crop, width - crop, 3, generator=gen, dtype=torch.float64)
    truth, truth_grad = _map_and_grad(pred, target, window, padding, weights, kornia=True)
    ours, ours_grad = _map_and_grad(pred, target, window, padding, weights, kornia=False)
    assert ours.shape == truth.shape
    scale = max(float(truth_grad.abs().max()), 1.0)
    assert float((ours - truth).abs().max()) <= 1e-13
    assert float((ours_grad - truth_grad).abs().max()) <= 1e-13 * scale
    pred32, target32, weights32 = pred.float(), target.float(), weights.float()
    ours32, ours32_grad = _map_and_grad(pred32, target32, window, padding, weights32, kornia=False)
    assert ours32.dtype == ours32_grad.dtype == torch.float32
    assert float((ours32.double() - truth).abs().max()) <= 2e-6
    assert float((ours32_grad.double() - truth_grad).abs().max()) <= 1e-6 * scale


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ssims_window_is_kornias_built_once(dtype: torch.dtype) -> None:
    cpu = torch.device("cpu")
    taps = ssim_taps(11, cpu, dtype)
    assert torch.equal(taps, get_gaussian_kernel1d(11, 1.5, device=cpu, dtype=dtype))
    assert taps.dtype == dtype and not taps.requires_grad
    assert ssim_taps(11, cpu, dtype) is taps and ssim_taps(7, cpu, dtype).shape == (1, 7)

"""PSNR, SSIM and LPIPS (v0.1, AlexNet) against known values."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import cv2
import pytest
import torch

from dyngs.metrics import ALEXNET_FILE, LPIPS, LPIPS_LIN_FILE, load_lpips, psnr, ssim

WEIGHTS = Path(__file__).resolve().parents[1] / ".." / "shared" / "weights"
TORCH_HOME = WEIGHTS / "torch-home"
CHECK = WEIGHTS / "lpips-check"

needs_weights = pytest.mark.skipif(
    not all(
        (TORCH_HOME / "hub" / "checkpoints" / f).is_file() for f in (ALEXNET_FILE, LPIPS_LIN_FILE)
    )
    or not CHECK.is_dir(),
    reason="LPIPS weights and check images not found under ../shared/weights",
)


def _read(name: str) -> torch.Tensor:
    bgr = cv2.imread(str(CHECK / name), cv2.IMREAD_COLOR)
    assert bgr is not None, name
    return torch.from_numpy(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)).float() / 255.0


def _rand(*shape: int, seed: int = 0) -> torch.Tensor:
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed))


# ---------------------------------------------------------------- PSNR, SSIM


def test_psnr_of_a_known_mse() -> None:
    target = torch.zeros(4, 5, 3, dtype=torch.float64)
    assert psnr(target + 0.1, target).item() == pytest.approx(20.0)  # MSE 0.01
    pred = target.clone()
    pred[0, 0, 0] = 1.0  # MSE 1/60
    assert psnr(pred, target).item() == pytest.approx(10 * math.log10(60))


def test_psnr_of_identical_images_is_infinite() -> None:
    x = _rand(3, 3, 3)
    assert psnr(x, x).item() == math.inf


def test_ssim_identical_and_constant() -> None:
    x = _rand(32, 32, 3)
    assert ssim(x, x).item() == pytest.approx(1.0, abs=1e-6)
    a = torch.full((16, 16, 3), 0.2, dtype=torch.float64)
    b = torch.full((16, 16, 3), 0.7, dtype=torch.float64)
    c1 = 0.01**2
    assert ssim(a, b).item() == pytest.approx((2 * 0.2 * 0.7 + c1) / (0.2**2 + 0.7**2 + c1))
    assert ssim(a, a).item() == 1.0


@pytest.mark.parametrize("size", [(1, 1), (5, 7), (10, 12), (11, 11)])
def test_ssim_of_small_images_is_finite(size: tuple[int, int]) -> None:
    value = ssim(_rand(*size, 3), _rand(*size, 3, seed=1))
    assert torch.isfinite(value) and -1.0 <= value.item() <= 1.0


def test_ssim_decreases_with_noise() -> None:
    x = _rand(48, 48, 3)
    noise = _rand(48, 48, 3, seed=1) - 0.5
    values = [ssim((x + s * noise).clamp(0, 1), x).item() for s in (0.0, 0.1, 0.3)]
    assert values[0] > values[1] > values[2]


# ---------------------------------------------------------------- LPIPS


@pytest.fixture
def lpips(monkeypatch: pytest.MonkeyPatch) -> LPIPS:
    monkeypatch.setenv("TORCH_HOME", str(TORCH_HOME))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # present weights load without a warning
        model = load_lpips("cpu")
    assert model is not None
    return model


@needs_weights
def test_lpips_published_values(lpips: LPIPS) -> None:
    ref, p0, p1 = _read("ex_ref.png"), _read("ex_p0.png"), _read("ex_p1.png")
    with torch.no_grad():
        # The LPIPS authors' values for v0.1 alex (lpips_2imgs.py on these images).
        assert round(lpips(ref, p0).item(), 3) == 0.722
        assert round(lpips(ref, p1).item(), 3) == 0.138
        batched = lpips(torch.stack([ref, ref]), torch.stack([p0, p1]))
    assert batched.shape == (2,)
    torch.testing.assert_close(batched, torch.stack([lpips(ref, p0), lpips(ref, p1)]))


@needs_weights
def test_lpips_of_an_image_with_itself_is_zero(lpips: LPIPS) -> None:
    x = _rand(40, 48, 3)
    assert lpips(x, x).item() == 0.0


@needs_weights
def test_lpips_gradient_reaches_the_image(lpips: LPIPS) -> None:
    x = _rand(40, 40, 3).requires_grad_()
    lpips(x, _rand(40, 40, 3, seed=1)).backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    assert all(p.grad is None for p in lpips.parameters())


@needs_weights
def test_lpips_rejects_images_smaller_than_alexnet_accepts(lpips: LPIPS) -> None:
    ok = _rand(LPIPS.MIN_SIZE, LPIPS.MIN_SIZE, 3)
    assert torch.isfinite(lpips(ok, ok.flip(0)))
    small = _rand(LPIPS.MIN_SIZE - 1, 64, 3)
    with pytest.raises(ValueError, match="at least"):
        lpips(small, small)


def test_absent_weights_give_none_and_one_warning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    with pytest.warns(UserWarning) as record:
        assert load_lpips("cpu") is None
    assert len(record) == 1
    message = str(record[0].message)
    assert ALEXNET_FILE in message and LPIPS_LIN_FILE in message and "null" in message


def test_failed_download_gives_none_and_one_warning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))

    def offline(*args: object, **kwargs: object) -> None:
        raise OSError("network is unreachable")

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", offline)
    with pytest.warns(UserWarning) as record:
        assert load_lpips("cpu", download=True) is None
    assert len(record) == 1
    assert "unreachable" in str(record[0].message)

"""Image reading (channel order, 16-bit, grayscale), compositing and downscaling."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from dyngs.datamanagers.images import composite, downscale, read_image
from dyngs.errors import DatasetError


def test_read_image_converts_to_rgb_and_8_bit(tmp_path: Path) -> None:
    bgra = np.zeros((2, 3, 4), np.uint8)
    bgra[0, 0] = (10, 20, 30, 40)  # B, G, R, A on disk
    cv2.imwrite(str(tmp_path / "rgba.png"), bgra)
    assert read_image(tmp_path / "rgba.png")[0, 0].tolist() == [30, 20, 10, 40]

    deep = np.full((2, 2, 3), 65535, np.uint16)
    deep[0, 0] = (257, 0, 514)
    cv2.imwrite(str(tmp_path / "deep.png"), deep)
    image = read_image(tmp_path / "deep.png")
    assert image.dtype == np.uint8
    assert image[0, 0].tolist() == [2, 0, 1] and image[1, 1].tolist() == [255, 255, 255]

    cv2.imwrite(str(tmp_path / "gray.png"), np.full((4, 5), 77, np.uint8))
    gray = read_image(tmp_path / "gray.png")
    assert gray.shape == (4, 5, 3) and (gray == 77).all()


def test_read_image_errors_are_one_line(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="missing image"):
        read_image(tmp_path / "nope.png")
    (tmp_path / "bad.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(DatasetError, match="cannot read image") as info:
        read_image(tmp_path / "bad.png")
    assert "bad.png" in str(info.value) and "\n" not in str(info.value)


def test_composite_by_hand() -> None:
    rgba = np.array([[[200, 100, 50, 128], [1, 2, 3, 255], [9, 9, 9, 0]]], np.uint8)
    out = composite(rgba, (0.2, 0.4, 0.6))
    # 200·128/255 + 0.2·255·127/255 = 100.39 + 25.4 = 125.79 → 126, and so on.
    assert out[0, 0].tolist() == [126, 101, 101]
    assert out[0, 1].tolist() == [1, 2, 3]  # opaque: the colour itself
    assert out[0, 2].tolist() == [51, 102, 153]  # transparent: the background


def test_downscale_rounds_odd_sizes() -> None:
    image = np.arange(7 * 5 * 3, dtype=np.uint8).reshape(5, 7, 3)
    assert downscale(image, 2).shape == (2, 4, 3)  # round(3.5) = 4, round(2.5) = 2
    mask = np.full((8, 6, 1), 255, np.uint8)
    assert downscale(mask, 2).shape == (4, 3, 1)  # the channel axis survives
    flat = np.full((8, 8, 3), 100, np.uint8)
    flat[:4, :4] = 0
    assert downscale(flat, 4)[0, 0].tolist() == [0, 0, 0]
    assert downscale(flat, 4)[1, 1].tolist() == [100, 100, 100]

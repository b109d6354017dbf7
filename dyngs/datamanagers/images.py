"""Image reading, alpha compositing and integer downscaling (OpenCV, uint8 in and out).

Letters: H×W image, C channels (3 or 4).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from jaxtyping import UInt8

from dyngs.datamanagers.base import DatasetError


def read_image(path: Path | str) -> UInt8[np.ndarray, "H W C"]:
    """RGB or RGBA uint8 of any PNG/JPEG/… OpenCV reads.

    16-bit images are scaled to 8 bits, grayscale is expanded to RGB (grayscale + alpha to
    RGBA). Raises a one-line DatasetError for a missing or unreadable file.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: missing image")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.size == 0:
        raise DatasetError(f"{path}: cannot read image")
    if image.dtype == np.uint16:
        # 65535 / 257 = 255 exactly, so the scaling maps full range onto full range.
        image = np.round(image.astype(np.float32) / 257.0).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise DatasetError(f"{path}: cannot read image of type {image.dtype} (need 8 or 16 bit)")
    if image.ndim == 2:
        image = image[:, :, None]
    channels = image.shape[2]
    if channels == 1:
        return np.ascontiguousarray(np.repeat(image, 3, axis=2))
    if channels == 2:
        gray, alpha = image[:, :, :1], image[:, :, 1:]
        return np.ascontiguousarray(np.concatenate([gray, gray, gray, alpha], axis=2))
    if channels == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if channels == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA)
    raise DatasetError(f"{path}: cannot read image with {channels} channels")


def composite(
    rgba: UInt8[np.ndarray, "H W 4"], background: tuple[float, float, float]
) -> UInt8[np.ndarray, "H W 3"]:
    """Straight-alpha RGBA over a solid background (RGB in [0, 1]), rounded back to uint8.

    out = round(255 · (c·α + b·(1 − α))) with c, α in [0, 1], computed in float64 once
    for each of the 256 × 256 (c, α) pairs and looked up per pixel: exact, and twice as
    fast as the float arithmetic over a full-size frame.
    """
    value = np.arange(256, dtype=np.float64)[:, None] / 255.0
    alpha = np.arange(256, dtype=np.float64)[None, :] / 255.0
    alpha_index = rgba[:, :, 3].astype(np.intp)
    out = np.empty((*rgba.shape[:2], 3), dtype=np.uint8)
    for channel in range(3):
        blended = value * alpha + background[channel] * (1.0 - alpha)
        table = np.clip(np.rint(blended * 255.0), 0, 255).astype(np.uint8).ravel()
        index = rgba[:, :, channel].astype(np.intp) * 256
        index += alpha_index
        out[:, :, channel] = table[index]
    return out


def downscaled_size(width: int, height: int, factor: int) -> tuple[int, int]:
    """(width, height) after dividing by `factor`, computed exactly as
    `Camera.scaled(1 / factor)` computes it, so image and camera always agree."""
    scale = 1.0 / factor
    return max(1, round(width * scale)), max(1, round(height * scale))


def downscale(image: UInt8[np.ndarray, "H W C"], factor: int) -> UInt8[np.ndarray, "h w C"]:
    """Shrink by an integer factor with area averaging (cv2.INTER_AREA).

    When a side is not divisible by `factor` it is resized to round(side / factor); the
    camera must then be scaled by the actual ratio, which `Camera.scaled` does.
    """
    if factor < 1:
        raise ValueError(f"downscale factor must be ≥ 1, got {factor}")
    if factor == 1:
        return image
    height, width = image.shape[:2]
    size = downscaled_size(width, height, factor)
    out = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    if out.ndim == 2:  # OpenCV drops a single channel axis
        out = out[:, :, None]
    return out

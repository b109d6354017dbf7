"""Image reading, alpha compositing, integer downscaling and lens undistortion (OpenCV,
uint8 in and out).

Letters: H×W image, C channels (3 or 4).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from jaxtyping import Float, UInt8

from dyngs.errors import DatasetError


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


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG's header (24 bytes read), or None if it is not a PNG.

    Lets a parser check every image's size up front without decoding any of them.
    """
    try:
        with Path(path).open("rb") as stream:
            head = stream.read(24)
    except OSError as error:
        raise DatasetError(f"{path}: cannot read ({error.strerror})") from None
    if len(head) < 24 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


@dataclass(frozen=True)
class Lens:
    """A camera with the radial-tangential distortion of OpenCV (and Nerfies, whose model
    is the same): normalised (x, y) → distorted (x', y') with r² = x² + y² and

        x' = x·(1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2x²)
        y' = y·(1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p2 x y + p1 (r² + 2y²)

    then pixel (fx x' + skew y' + cx, fy y' + cy), pixel centres at +0.5.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    skew: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    @property
    def is_pinhole(self) -> bool:
        """No distortion and no skew: the image needs no resampling."""
        return not any((self.skew, self.k1, self.k2, self.k3, self.p1, self.p2))

    def distort(
        self, x: Float[np.ndarray, "*shape"], y: Float[np.ndarray, "*shape"]
    ) -> tuple[Float[np.ndarray, "*shape"], Float[np.ndarray, "*shape"]]:
        """Pixel coordinates of normalised image-plane points."""
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * radial + 2.0 * self.p2 * x * y + self.p1 * (r2 + 2.0 * y * y)
        return self.fx * xd + self.skew * yd + self.cx, self.fy * yd + self.cy


@functools.lru_cache(maxsize=8)
def _undistort_maps(
    lens: Lens, fx: float, fy: float, cx: float, cy: float, width: int, height: int
) -> tuple[Float[np.ndarray, "h w"], Float[np.ndarray, "h w"]]:
    u = (np.arange(width, dtype=np.float64) + 0.5 - cx) / fx
    v = (np.arange(height, dtype=np.float64) + 0.5 - cy) / fy
    x, y = np.meshgrid(u, v)
    px, py = lens.distort(x, y)
    # OpenCV samples at integer pixel centres: shift our +0.5 centres back.
    return (px - 0.5).astype(np.float32), (py - 0.5).astype(np.float32)


def undistort(
    image: UInt8[np.ndarray, "H W C"],
    lens: Lens,
    pinhole: tuple[float, float, float, float],
    size: tuple[int, int],
) -> UInt8[np.ndarray, "h w C"]:
    """The image a distortion-free camera (fx, fy, cx, cy) = `pinhole` of `size` (width,
    height) sees, resampled (bilinear) from `image`, taken through `lens`.

    Each output pixel centre is cast as a ray of the pinhole camera and looked up where
    the lens puts that ray. Rays landing outside the source repeat its border pixel.
    The sampling maps are cached for the last few distinct cameras.
    """
    map_x, map_y = _undistort_maps(lens, *pinhole, *size)
    out = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if out.ndim == 2:
        out = out[:, :, None]
    return out

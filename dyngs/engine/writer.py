"""Where training reports go: a small Writer protocol and its TensorBoard implementation.

The trainer receives its writer; nothing here is global.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
from jaxtyping import Float
from torch import Tensor


class Writer(Protocol):
    def scalar(self, tag: str, value: float, step: int) -> None: ...

    def image(self, tag: str, image: Float[Tensor, "H W 3"], step: int) -> None: ...

    def flush(self) -> None: ...

    def close(self) -> None: ...


class NullWriter:
    """Discards everything (tests, `--no-tensorboard`)."""

    def scalar(self, tag: str, value: float, step: int) -> None:
        pass

    def image(self, tag: str, image: Float[Tensor, "H W 3"], step: int) -> None:
        pass

    def flush(self) -> None:
        pass

    def close(self) -> None:
        pass


def to_uint8(image: Float[Tensor, "H W 3"]) -> np.ndarray:
    return (image.detach().float().clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)


def encode_png(image: Float[Tensor, "H W 3"]) -> bytes:
    ok, data = cv2.imencode(".png", cv2.cvtColor(to_uint8(image), cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return data.tobytes()


class TensorBoardWriter:
    """Event files under `log_dir`, readable with `tensorboard --logdir RUN`."""

    def __init__(self, log_dir: Path) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self._writer = SummaryWriter(str(log_dir))

    def scalar(self, tag: str, value: float, step: int) -> None:
        self._writer.add_scalar(tag, value, step)

    def image(self, tag: str, image: Float[Tensor, "H W 3"], step: int) -> None:
        # SummaryWriter.add_image needs Pillow; the image summary proto only wants PNG
        # bytes, which OpenCV already gives us.
        from tensorboard.compat.proto.summary_pb2 import Summary

        height, width = image.shape[:2]
        proto = Summary.Image(
            height=height, width=width, colorspace=3, encoded_image_string=encode_png(image)
        )
        summary = Summary(value=[Summary.Value(tag=tag, image=proto)])
        self._writer._get_file_writer().add_summary(summary, step)

    def flush(self) -> None:
        self._writer.flush()

    def close(self) -> None:
        self._writer.close()

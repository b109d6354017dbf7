"""Adaptive resolution: small frames while the view moves, the full frame once it stops.

A CPU renderer cannot draw a large frame at an interactive rate, but most of its time
goes into pixels. While the camera moves or time plays, each frame's long side is scaled
so that the frame time meets a target; when the view has been still for a moment, one
frame at the full size replaces the last small one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

SETTLE_SECONDS = 0.25
"""The view counts as moving until this long after the camera's last change: mouse
drags send camera updates at the browser's frame rate, so a longer gap means it stopped."""
DAMPING = 0.5
"""Each moving frame moves the scale this share of the way (in log scale) to the one
that would have met the target; damping keeps it from oscillating on noisy timings."""


@dataclass
class AdaptiveResolution:
    """Chooses each frame's long side from the time the last moving frames took.

    The frame time is taken as proportional to the pixel count, so the scale that meets
    the target is the current one times sqrt(target / measured); a render whose fixed
    cost (deformation, projection) alone exceeds the target drives it to `min_scale`.
    """

    full_side: int
    """Long side of a still frame, in pixels."""
    target_seconds: float
    """Frame time to meet while moving (1 / the frame rate aimed at)."""
    min_side: int = 64
    """Long side of a moving frame is never below this (or `full_side`, if smaller)."""
    scale: float = 0.5
    """The current moving scale, in (0, 1]; starts at half size and adapts."""

    def __post_init__(self) -> None:
        if self.full_side < 1:
            raise ValueError(f"full_side must be ≥ 1, got {self.full_side}")
        if not self.target_seconds > 0:
            raise ValueError(f"target_seconds must be positive, got {self.target_seconds}")

    @property
    def min_scale(self) -> float:
        return min(1.0, self.min_side / self.full_side)

    def side(self, moving: bool) -> int:
        """Long side of the next frame: scaled while `moving`, else the full one."""
        if not moving:
            return self.full_side
        return max(1, round(self.full_side * max(self.scale, self.min_scale)))

    def measured(self, side: int, seconds: float) -> None:
        """Record that a frame with long side `side` took `seconds`; frames at the full
        side teach the moving scale too (the first still frame sets it from the start)."""
        if seconds <= 0 or side < 1:
            return
        used = side / self.full_side
        ideal = used * math.sqrt(self.target_seconds / seconds)
        step = math.exp(DAMPING * math.log(ideal / max(self.scale, 1e-9)))
        self.scale = min(1.0, max(self.min_scale, self.scale * step))

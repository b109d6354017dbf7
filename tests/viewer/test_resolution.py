"""Adaptive resolution: full frames when still, frames that meet the target while moving."""

from __future__ import annotations

import pytest

from dyngs.viewer.resolution import AdaptiveResolution


def _simulate(fixed: float, per_pixel: float, frames: int = 30) -> AdaptiveResolution:
    """Moving frames on a renderer that takes fixed + per_pixel · side² seconds."""
    adaptive = AdaptiveResolution(full_side=800, target_seconds=0.1)
    for _ in range(frames):
        side = adaptive.side(moving=True)
        adaptive.measured(side, fixed + per_pixel * side * side)
    return adaptive


def test_still_frames_are_full_size() -> None:
    adaptive = AdaptiveResolution(full_side=800, target_seconds=0.1)
    assert adaptive.side(moving=False) == 800
    assert adaptive.side(moving=True) == 400  # half size until it has measured a frame


def test_moving_frames_converge_to_the_target_time() -> None:
    adaptive = _simulate(fixed=0.0, per_pixel=0.4 / 800**2)  # full frame: 0.4 s
    side = adaptive.side(moving=True)
    assert side == pytest.approx(400, abs=2)  # a quarter of the pixels: 0.1 s


def test_a_fast_renderer_draws_full_size_while_moving() -> None:
    adaptive = _simulate(fixed=0.0, per_pixel=0.01 / 800**2)
    assert adaptive.side(moving=True) == 800


def test_a_fixed_cost_over_the_target_gives_the_smallest_frames() -> None:
    adaptive = _simulate(fixed=0.2, per_pixel=1e-9)
    assert adaptive.side(moving=True) == 64


def test_a_full_frame_teaches_the_moving_scale() -> None:
    adaptive = AdaptiveResolution(full_side=800, target_seconds=0.1)
    for _ in range(20):
        adaptive.measured(800, 1.6)  # a still frame 16 times over the target
    assert adaptive.side(moving=True) == pytest.approx(200, abs=2)


def test_bad_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="full_side"):
        AdaptiveResolution(full_side=0, target_seconds=0.1)
    with pytest.raises(ValueError, match="target_seconds"):
        AdaptiveResolution(full_side=10, target_seconds=0.0)

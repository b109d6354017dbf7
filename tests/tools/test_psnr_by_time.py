"""benchmarks/psnr_by_time.py: frames land in the right span of t, and bad runs are skipped."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.tools.conftest import load_benchmark

psnr_by_time = load_benchmark("psnr_by_time")


def test_frames_are_averaged_within_their_span_and_t_1_is_in_the_last() -> None:
    frames = [
        {"time": 0.0, "psnr": 30.0},
        {"time": 0.19, "psnr": 32.0},
        {"time": 0.5, "psnr": 20.0},
        {"time": 1.0, "psnr": 25.0},
    ]
    assert psnr_by_time.by_time(frames, 5) == [31.0, None, 20.0, None, 25.0]
    assert psnr_by_time.by_time(frames, 1) == [pytest.approx(26.75)]


def test_a_run_without_its_evaluation_is_skipped(tmp_path: Path) -> None:
    assert psnr_by_time.summarize(tmp_path, "test", 2) is None
    (tmp_path / "config.json").write_text(json.dumps({"seed": 3}))
    frames = [{"time": 0.2, "psnr": 28.0}, {"time": 0.8, "psnr": 24.0}]
    (tmp_path / "eval_test.json").write_text(json.dumps({"psnr": 26.0, "frames": frames}))
    row = psnr_by_time.summarize(tmp_path, "test", 2)
    assert row == {"run": str(tmp_path), "seed": 3, "psnr": 26.0, "psnr_by_time": [28.0, 24.0]}

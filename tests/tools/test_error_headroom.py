"""benchmarks/error_headroom.py: error lands in the right region, the pairs are read
render-first, and a blurred ground truth scores what a blur of it scores."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.tools.conftest import load_benchmark

error_headroom = load_benchmark("error_headroom")

WHITE = np.ones(3, np.float32)


def square_scene() -> np.ndarray:
    """A white 24×24 image with a black 10×10 square in the middle."""
    truth = np.ones((24, 24, 3), np.float32)
    truth[7:17, 7:17] = 0.0
    return truth


def test_error_inside_the_foreground_is_counted_inside() -> None:
    truth = square_scene()
    render = truth.copy()
    render[11:13, 11:13] = 0.5  # well inside the square, beyond the 2 px band
    shares = error_headroom.error_shares([(render, truth)], WHITE, 0.05, 2)
    assert shares == {"inside": pytest.approx(1.0), "edge": 0.0, "elsewhere": 0.0}


def test_a_shifted_edge_is_counted_on_the_edge() -> None:
    truth = square_scene()
    render = np.roll(truth, 1, axis=1)  # the square one pixel to the right
    shares = error_headroom.error_shares([(render, truth)], WHITE, 0.05, 2)
    assert shares["edge"] == pytest.approx(1.0)


def test_error_far_from_everything_is_elsewhere() -> None:
    truth = square_scene()
    render = truth.copy()
    render[0:2, 20:24] = 0.0
    shares = error_headroom.error_shares([(render, truth)], WHITE, 0.05, 2)
    assert shares["elsewhere"] == pytest.approx(1.0)


def write_run(folder: Path, render: np.ndarray, truth: np.ndarray) -> None:
    (folder / "test").mkdir(parents=True)
    (folder / "config.json").write_text(
        json.dumps({"seed": 4, "dataset": {"background": [1, 1, 1]}})
    )
    pair = (np.concatenate([render, truth], axis=1) * 255).round().astype(np.uint8)
    cv2.imwrite(str(folder / "test" / "0000.png"), cv2.cvtColor(pair, cv2.COLOR_RGB2BGR))


def test_a_run_is_read_render_first_and_its_blur_figures_are_the_truths(tmp_path: Path) -> None:
    truth = square_scene()
    render = truth.copy()
    render[11:13, 11:13] = 0.5
    write_run(tmp_path, render, truth)
    row = error_headroom.headroom(tmp_path, "test", [1.0], 0.05, 2)
    assert row["seed"] == 4
    # Only the four grey pixels differ: (4 · 3 · 0.5²) / (24 · 24 · 3) of squared error.
    expected = -10 * np.log10(4 * 3 * (128 / 255) ** 2 / (24 * 24 * 3))
    assert row["psnr"] == pytest.approx(expected, abs=1e-4)
    blurred = cv2.GaussianBlur(truth, (0, 0), 1.0)
    blur_psnr = -10 * np.log10(((blurred - truth) ** 2).mean())
    assert row["truth_blurred_psnr"]["1"] == pytest.approx(blur_psnr, rel=1e-5)
    assert row["error_share"]["inside"] == pytest.approx(1.0)


def test_a_run_without_images_is_one_clear_error(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="no render \\| ground-truth images"):
        error_headroom.pairs(tmp_path, "test")

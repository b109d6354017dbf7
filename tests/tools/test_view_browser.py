"""dyngs-view in a real browser: the system's Chromium, headless, opens the page; the time
slider is moved with the keyboard, as a user would; the frame the page draws, read back
from its WebGL canvas, must change and match dyngs-render of the same camera and time.

The tolerance: the page receives each frame as a JPEG (quality `JPEG_QUALITY`) and draws
it into a canvas of the frame's own size, so the only expected difference from
dyngs-render's frame is JPEG's. The test measures that loss on the reference frame
itself (OpenCV's encoder and decoder at the same quality) and allows the page
`DECODER_SLACK_DB` less, for the browser's own JPEG decoder and chroma upsampling. A
wrong camera, time or colour space costs far more: the two times' frames differ by more
than the tolerance (asserted), and a one-pixel shift of the camera would too.

Chromium is a system package (`apt-get install chromium`; .ci/run installs it): where it
is missing this test fails, saying so, rather than skipping.
"""

from __future__ import annotations

import base64
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from dyngs.runs import load_run
from dyngs.tools.render import RenderConfig, camera_path, render_frame, resize_camera
from dyngs.tools.view import ViewConfig, load_for_viewing
from dyngs.viewer.options import ViewerOptions
from dyngs.viewer.server import FrameRecord, Viewer

pytestmark = pytest.mark.slow

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_FLAGS = [
    "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]  # fmt: skip
"""Headless on a machine without a GPU or network: WebGL runs on SwiftShader (Chromium's
software fallback), and no background connection is tried."""
SIZE = 256
"""The page is SIZE × SIZE pixels, so the canvas has the square training camera's aspect
and the full-size frame is drawn one frame pixel per canvas pixel."""
JPEG_QUALITY = 90
DECODER_SLACK_DB = 3.0
WAIT_SECONDS = 600.0
"""How long the page may take to show a frame (a condition polled, not a sleep): a guard
against a hang, not a speed limit. A page shows its frame in a few seconds on an idle
machine, but 60 s were too few when the suite ran beside another whole suite on two
cores: the test must not depend on how busy the machine is."""


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * np.log10(255.0**2 / max(mse, 1e-12))


def jpeg_round_trip(image: np.ndarray, quality: int) -> np.ndarray:
    ok, data = cv2.imencode(".jpg", image[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    decoded = cv2.imdecode(data, cv2.IMREAD_COLOR)
    assert decoded is not None
    return decoded[..., ::-1]


def wait_for(condition: Callable[[], bool], what: Callable[[], str]) -> None:
    """Poll `condition` until it holds; fail after WAIT_SECONDS, saying `what()`."""
    deadline = time.monotonic() + WAIT_SECONDS
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"gave up after {WAIT_SECONDS:.0f} s: {what()}")
        time.sleep(0.1)


@pytest.fixture(scope="module")
def viewer(fading_run: Path) -> Iterator[Viewer]:
    options = ViewerOptions(host="127.0.0.1", port=0, max_side=SIZE, jpeg_quality=JPEG_QUALITY)
    run = load_for_viewing(ViewConfig(load_dir=fading_run, viewer=options))  # as dyngs-view
    viewer = Viewer(run.scene, run.renderer, options)
    viewer.show(run.model)
    viewer.start()
    yield viewer
    viewer.stop()


@pytest.fixture(scope="module")
def page(viewer: Viewer) -> Iterator[Any]:
    if shutil.which(CHROMIUM) is None:
        pytest.fail(f"{CHROMIUM} is missing: install Chromium (`apt-get install chromium`)")
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as profile, sync_playwright() as playwright:
        browser = playwright.chromium.launch_persistent_context(
            profile, executable_path=CHROMIUM, headless=True, args=CHROMIUM_FLAGS,
            viewport={"width": SIZE, "height": SIZE},
        )  # fmt: skip
        page = browser.pages[0] if browser.pages else browser.new_page()
        page.goto(viewer.url)
        yield page
        browser.close()


CANVAS_PNG = """() => {
    const canvases = Array.from(document.querySelectorAll('canvas'));
    if (canvases.length === 0) return null;
    const c = canvases.reduce((a, b) => (a.width * a.height >= b.width * b.height ? a : b));
    return c.toDataURL('image/png');
}"""
"""The page's largest canvas (three.js's; viser draws the frame into it) as a PNG; null
while the page has none yet."""


def canvas_image(page: Any) -> np.ndarray:
    url = page.evaluate(CANVAS_PNG)
    if url is None:
        return np.zeros((0, 0, 3), dtype=np.uint8)  # not drawn yet: matches nothing
    data = np.frombuffer(base64.b64decode(url.split(",", 1)[1]), dtype=np.uint8)
    decoded = cv2.imdecode(data, cv2.IMREAD_COLOR)
    assert decoded is not None, "the canvas gave no PNG"
    return decoded[..., ::-1]


def last_frame(viewer: Viewer) -> FrameRecord | None:
    """The last frame the viewer sent the page (the test opens one page: one client)."""
    records = list(viewer.frames.values())
    assert len(records) <= 1, f"{len(records)} clients: the test opens one page"
    return records[0] if records else None


def describe(record: FrameRecord | None) -> str:
    if record is None:
        return "no frame"
    size = f"{record.camera.width}×{record.camera.height}"
    kind = "full-size" if record.refined else "a smaller moving"
    return f"{kind} frame, {size}, t = {record.time}"


def reference(run_dir: Path, t: float) -> np.ndarray:
    """dyngs-render's frame of the first training camera at time t (`--trajectory fixed
    --split train --camera 0 --frames 2` renders t = 0 and t = 1) at SIZE × SIZE."""
    config = RenderConfig(load_dir=run_dir, trajectory="fixed", split="train", camera=0,
                          frames=2, width=SIZE, height=SIZE)  # fmt: skip
    run = load_run(run_dir)
    frames = {time_: camera for camera, time_ in camera_path(run, config)}
    camera = resize_camera(frames[t], 1.0, SIZE, SIZE)
    return render_frame(run, camera, t)


def test_the_time_slider_changes_the_drawn_frame_as_dyngs_render_draws_it(
    viewer: Viewer, page: Any, fading_run: Path
) -> None:
    expected = {t: reference(fading_run, t) for t in (0.0, 1.0)}
    jpeg_db = psnr(jpeg_round_trip(expected[0.0], JPEG_QUALITY), expected[0.0])
    tolerance = jpeg_db - DECODER_SLACK_DB
    assert psnr(expected[0.0], expected[1.0]) < tolerance - 3.0  # the two times tell apart
    seen: dict[float, np.ndarray] = {}

    def shows(t: float) -> bool:
        # The page may first get smaller frames drawn while its view settles (how small
        # depends on how fast the machine draws): only the full-size frame of time t,
        # the viewer's last, is compared, and its camera checked below.
        seen[t] = canvas_image(page)
        last = last_frame(viewer)
        return (
            last is not None and last.refined and last.time == t
            and seen[t].shape[:2] == (SIZE, SIZE) and psnr(seen[t], expected[t]) >= tolerance
        )  # fmt: skip

    def said(t: float) -> Callable[[], str]:
        def text() -> str:
            got = seen.get(t)
            if got is None or got.shape[:2] != (SIZE, SIZE):
                fit = "no canvas" if got is None else f"canvas {got.shape[:2]}"
            else:
                fit = f"{psnr(got, expected[t]):.1f} dB"
            return (f"the page never showed t = {t} ({fit}; needs {tolerance:.1f} dB); "
                    f"the viewer last sent {describe(last_frame(viewer))}")  # fmt: skip

        return text

    wait_for(lambda: shows(0.0), said(0.0))
    record = last_frame(viewer)
    assert record is not None
    drawn = record.camera
    first_view = resize_camera(viewer.scene.train.cameras[0], 1.0, SIZE, SIZE)
    assert np.allclose(drawn.world_to_camera.numpy(), first_view.world_to_camera.numpy(),
                       atol=1e-6)  # fmt: skip
    assert drawn.fy == pytest.approx(first_view.fy)

    slider = page.get_by_role("slider").first  # Time, the first control on the page
    slider.focus()
    slider.press("End")
    assert slider.get_attribute("aria-valuenow") == "1"
    wait_for(lambda: shows(1.0), said(1.0))
    assert psnr(seen[0.0], seen[1.0]) < tolerance  # the drawn frame changed


def test_play_runs_time_and_reports_the_frame_rate(viewer: Viewer, page: Any) -> None:
    slider = page.get_by_role("slider").first
    start = slider.get_attribute("aria-valuenow")
    page.get_by_role("button", name="Play").click()
    wait_for(lambda: slider.get_attribute("aria-valuenow") != start,
             lambda: f"the time slider stayed at {start} while playing")  # fmt: skip
    wait_for(lambda: page.get_by_text("frames/s").count() > 0,
             lambda: "no frame rate on the page")  # fmt: skip
    page.get_by_role("button", name="Pause").click()
    # The click reaches the server over the page's websocket, after click() returns.
    assert viewer.controls is not None
    controls = viewer.controls
    wait_for(lambda: not controls.state.playing, lambda: "still playing after Pause")


def test_static_dynamic_colours_reach_the_page(viewer: Viewer, page: Any) -> None:
    page.get_by_role("slider").first.press("Home")  # t = 0, where the dynamic ones live
    page.get_by_text("Static / dynamic").click()

    def shows_both() -> bool:
        # Orange (dynamic) is red over blue, blue (static) the reverse; both blend into
        # the white background at their edges, so the test looks at hue, not exact values.
        image = canvas_image(page).astype(np.int32)
        red_minus_blue = image[..., 0] - image[..., 2]
        if image.size == 0:
            return False
        return bool((red_minus_blue > 60).mean() > 0.01 and (red_minus_blue < -60).mean() > 0.01)

    wait_for(shows_both, lambda: "the page never showed static and dynamic Gaussians in colour")

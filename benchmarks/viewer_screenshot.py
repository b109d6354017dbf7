"""A screenshot of dyngs-view for the docs, taken the way the browser test drives the page.

    python benchmarks/viewer_screenshot.py --run outputs/RUN --output docs/viewer.png

Serves the run's viewer on a free local port, opens it in the system's headless Chromium
(the browser test's flags), sets the time slider to `--time` and the camera to `--view`,
waits for the full-size frame and saves the page (controls included) as a PNG.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dyngs.tools.view import ViewConfig, load_for_viewing  # noqa: E402
from dyngs.viewer.options import ViewerOptions  # noqa: E402
from dyngs.viewer.server import FrameRecord, Viewer  # noqa: E402
from tests.tools.test_view_browser import CHROMIUM, CHROMIUM_FLAGS  # noqa: E402


def wait_for_full_frame(
    viewer: Viewer, t: float, centre: torch.Tensor | None = None, timeout: float = 120.0
) -> None:
    """Until a full-size frame at time t (from a camera at `centre`, if given) is sent."""

    def done(frame: FrameRecord) -> bool:
        there = centre is None or bool(
            torch.allclose(frame.camera.center.double(), centre, atol=1e-4)
        )
        return frame.refined and abs(frame.time - t) < 1e-6 and there

    deadline = time.monotonic() + timeout
    while not any(done(f) for f in list(viewer.frames.values())):
        if time.monotonic() > deadline:
            raise TimeoutError("the viewer drew no full-size frame")
        time.sleep(0.1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True)
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "viewer.png")
    parser.add_argument("--time", type=float, default=0.5)
    parser.add_argument("--view", default="test 0", help="an entry of the Camera list")
    parser.add_argument("--width", type=int, default=960)
    parser.add_argument("--height", type=int, default=600)
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright

    options = ViewerOptions(host="127.0.0.1", port=0)
    run = load_for_viewing(ViewConfig(load_dir=args.run, viewer=options))
    viewer = Viewer(run.scene, run.renderer, options, title=f"dyngs · {args.run.name}")
    viewer.show(run.model, f"step {run.step:,}")
    viewer.start()
    try:
        with tempfile.TemporaryDirectory() as profile, sync_playwright() as playwright:
            browser = playwright.chromium.launch_persistent_context(
                profile, executable_path=CHROMIUM, headless=True, args=CHROMIUM_FLAGS,
                viewport={"width": args.width, "height": args.height},
            )  # fmt: skip
            page = browser.pages[0] if browser.pages else browser.new_page()
            page.goto(viewer.url)
            wait_for_full_frame(viewer, 0.0)
            # The "software WebGL" notice is true here, and noise in the docs.
            notices = page.locator(".mantine-Notification-root")
            for close in page.locator(".mantine-Notification-closeButton").all():
                close.click()
            notices.first.wait_for(state="detached")
            assert viewer.controls is not None
            viewer.controls.view.value = args.view  # as picking it in the list does
            viewer.controls.time.value = args.time  # type: ignore[misc]
            centre = viewer.controls.views[args.view].center
            wait_for_full_frame(viewer, args.time, centre.to(torch.float64))
            time.sleep(1.0)  # the last frame's JPEG reaches the canvas
            page.screenshot(path=str(args.output))
            browser.close()
    finally:
        viewer.stop()
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()

"""What `dyngs-train --viewer` costs training, with a page open the whole run.

    python benchmarks/bench_viewer_training.py --max-iters 300 --rounds 2

Trains the demo scene for `--max-iters` steps without the viewer and with it (a headless
Chromium page, the browser test's flags, connected from the first step to the end),
alternating, `--rounds` times each. Reports the training step time (the run's
`train_seconds`: the steps alone, so what the page costs them through the shared CPU)
and, from the page, how long the step hook held training for its snapshots (median and
longest). Writes benchmarks/results/viewer-training.json with the command, commit and
machine.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dyngs.tools.common import machine_info, source_commit  # noqa: E402
from tests.tools.test_view_browser import CHROMIUM, CHROMIUM_FLAGS  # noqa: E402

HOOK_LINE = re.compile(r"snapshot ([0-9.]+) ms \(longest ([0-9.]+) ms\)")


def watch(url: str, done: threading.Event, seen: dict[str, float]) -> None:
    """Keep a page open on `url` until `done`, recording the hook's last reported times."""
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as profile, sync_playwright() as playwright:
        browser = playwright.chromium.launch_persistent_context(
            profile,
            executable_path=CHROMIUM,
            headless=True,
            args=CHROMIUM_FLAGS,
            viewport={"width": 800, "height": 600},
        )
        page = browser.pages[0] if browser.pages else browser.new_page()
        page.goto(url)
        while not done.wait(1.0):
            found = HOOK_LINE.search(page.content())
            if found:
                seen["median_ms"], seen["longest_ms"] = map(float, found.groups())
        browser.close()


def train(max_iters: int, viewer: bool) -> dict[str, Any]:
    out = Path(tempfile.mkdtemp(prefix="viewer-training-"))
    command = [
        "dyngs-train",
        "hexplane-4dgs",
        "--data",
        "demo",
        "--max-iters",
        str(max_iters),
        "--no-tensorboard",
        "--output-dir",
        str(out),
        "--run-name",
        "run",
    ]
    if viewer:
        command += ["--viewer", "--viewer-host", "127.0.0.1", "--viewer-port", "0"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert process.stdout is not None
    done, seen, watcher = threading.Event(), {}, None
    started = time.perf_counter()
    for line in process.stdout:
        found = re.search(r"viewer at (http://[0-9.]+:[0-9]+)", line)
        if found and watcher is None:
            watcher = threading.Thread(target=watch, args=(found.group(1), done, seen))
            watcher.start()
    process.wait()
    wall = time.perf_counter() - started
    done.set()
    if watcher is not None:
        watcher.join()
    assert process.returncode == 0, f"{command} failed"
    metrics = json.loads((out / "run" / "metrics.json").read_text())
    return {
        "viewer": viewer,
        "train_seconds": metrics["train_seconds"],
        "wall_seconds": wall,
        "hook": seen or None,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--max-iters", type=int, default=300)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument(
        "--output", type=Path, default=ROOT / "benchmarks" / "results" / "viewer-training.json"
    )
    args = parser.parse_args()
    runs = []
    for _ in range(args.rounds):
        for viewer in (False, True):
            runs.append(train(args.max_iters, viewer))
            print(runs[-1], flush=True)
    commit = source_commit(ROOT)
    summary = {
        mode: statistics.median(r["train_seconds"] for r in runs if r["viewer"] == (mode == "with"))
        for mode in ("without", "with")
    }
    result = {
        "command": " ".join(["python", *sys.argv]),
        "commit": commit,
        "machine": machine_info(),
        "load_average": os.getloadavg(),
        "env": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS")},
        "max_iters": args.max_iters,
        "median_train_seconds": summary,
        "runs": runs,
    }
    args.output.write_text(json.dumps(result, indent=2) + "\n")
    print(f"train seconds, median: without {summary['without']:.1f}, with {summary['with']:.1f}")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()

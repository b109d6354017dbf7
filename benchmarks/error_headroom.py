"""Where a run's test error lies, and what a PSNR target asks of a model.

    python benchmarks/error_headroom.py RUN [RUN ...] --output FILE

Reads the render | ground-truth pairs a run wrote at the end of training (RUN/test/*.png,
or RUN/eval_<split>/ from `dyngs-eval`) and reports, per run:

- the PSNR of the ground truth against itself blurred by a Gaussian of σ px, for each
  `--blur`: what a model with every surface in place and the right colours, but drawn
  that much softer, would score. It says how sharp a target PSNR requires the test views
  to be;
- the share of the squared error inside the foreground (pixels whose ground truth
  differs from the background colour by more than `--threshold`, eroded by `--band`
  px), on its boundary (within `--band` px of the foreground's edge) and elsewhere:
  whether a model loses on what things look like, or on where their edges are.

The background colour is the run's (`config.json`). Writes the figures to --output (JSON).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dyngs.metrics import psnr as torch_psnr  # noqa: E402
from dyngs.tools.common import write_report  # noqa: E402


def pairs(run: Path, split: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """(render, ground truth) of every view, float32 RGB in [0, 1]."""
    folder = run / split if (run / split).is_dir() else run / f"eval_{split}"
    files = sorted(folder.glob("*.png"))
    if not files:
        raise SystemExit(f"{run}: no render | ground-truth images in {folder}")
    out = []
    for file in files:
        image = cv2.imread(str(file))
        if image is None:
            raise SystemExit(f"{file}: not a readable image")
        pair = cv2.cvtColor(image, cv2.COLOR_BGR2RGB).astype(np.float32) / 255
        width = pair.shape[1] // 2
        out.append((pair[:, :width], pair[:, width:]))
    return out


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """`dyngs.metrics.psnr` of two float32 images, as the run's own evaluation scores them."""
    return float(torch_psnr(torch.from_numpy(a), torch.from_numpy(b)))


def error_shares(
    views: list[tuple[np.ndarray, np.ndarray]], background: np.ndarray, threshold: float, band: int
) -> dict:
    """Shares of the summed squared error inside the foreground, on its edge band, and
    elsewhere."""
    sums = np.zeros(3)
    kernel = np.ones((2 * band + 1, 2 * band + 1), np.uint8)
    for render, truth in views:
        ground = (np.abs(truth - background).max(axis=2) > threshold).astype(np.uint8)
        inside = cv2.erode(ground, kernel).astype(bool)
        edge = cv2.dilate(ground, kernel).astype(bool) & ~inside
        error = ((render - truth) ** 2).sum(axis=2)
        sums += [error[inside].sum(), error[edge].sum(), error[~(inside | edge)].sum()]
    shares = sums / max(sums.sum(), 1e-12)
    return {"inside": float(shares[0]), "edge": float(shares[1]), "elsewhere": float(shares[2])}


def headroom(run: Path, split: str, blurs: list[float], threshold: float, band: int) -> dict:
    views = pairs(run, split)
    config = json.loads((run / "config.json").read_text())
    background = np.asarray(config["dataset"]["background"], np.float32)
    truths = [truth for _, truth in views]
    blurred = {
        f"{sigma:g}": float(np.mean([psnr(cv2.GaussianBlur(t, (0, 0), sigma), t) for t in truths]))
        for sigma in blurs
    }
    return {
        "run": str(run),
        "seed": config.get("seed"),
        "psnr": float(np.mean([psnr(r, t) for r, t in views])),
        "truth_blurred_psnr": blurred,
        "error_share": error_shares(views, background, threshold, band),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--split", default="test", choices=("train", "val", "test"))
    parser.add_argument("--blur", type=float, nargs="+", default=[0.5, 0.7, 1.0, 1.5])
    parser.add_argument("--threshold", type=float, default=0.05)
    parser.add_argument("--band", type=int, default=2)
    parser.add_argument("--output", type=Path)
    args = parser.parse_args()
    if min(args.blur) <= 0 or args.band < 1:
        parser.error("--blur values must be > 0 and --band ≥ 1")
    rows = [headroom(run, args.split, args.blur, args.threshold, args.band) for run in args.runs]
    for row in rows:
        blurred = "  ".join(f"σ {s}: {p:.2f}" for s, p in row["truth_blurred_psnr"].items())
        shares = "  ".join(f"{k} {v:.0%}" for k, v in row["error_share"].items())
        print(f"{row['run']}  seed {row['seed']}  PSNR {row['psnr']:.2f}  "
              f"truth blurred: {blurred}  error: {shares}")  # fmt: skip
    if args.output:
        write_report(args.output, ROOT, 1, split=args.split, threshold=args.threshold,
                     band=args.band, runs=rows)  # fmt: skip


if __name__ == "__main__":
    main()

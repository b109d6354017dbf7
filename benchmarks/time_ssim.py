"""Time the training loss's SSIM map, forward and backward: dyngs' against kornia's.

    python benchmarks/time_ssim.py --threads 1 --sizes 100 128 270x480

`dyngs.losses.photometric.ssim_map` computes kornia's SSIM (Gaussian window σ = 1.5,
reflect padding, eps 0) with kornia's own window and separable filter, but filters the
five local moments (x, y, x², y², xy) in two calls, the prediction's three and the
target's two, where `kornia.metrics.ssim` makes five calls of three, and on a CPU both the
filter and the map from the moments are compiled. This script times one forward and
backward of each on random H×W×3 float32 images, interleaved over `--repeats` rounds,
and reports the medians, after checking that the two maps agree. It writes the figures to
`--output` as JSON.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from kornia.metrics import ssim as kornia_ssim

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dyngs.losses.photometric import SSIM_WINDOW, ssim_map  # noqa: E402
from dyngs.tools.common import write_report  # noqa: E402


def theirs(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    out = kornia_ssim(pred.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], SSIM_WINDOW,
                      max_val=1.0, eps=0.0)  # fmt: skip
    return out[0].permute(1, 2, 0)


def time_size(height: int, width: int, repeats: int) -> dict:
    """Medians over `repeats` interleaved rounds of one forward and backward of each."""
    gen = torch.Generator().manual_seed(0)
    target = torch.rand(height, width, 3, generator=gen)
    pred = torch.rand(height, width, 3, generator=gen, requires_grad=True)
    with torch.no_grad():
        diff = float((ssim_map(pred, target) - theirs(pred, target)).abs().max())
    assert diff < 1e-5, f"the maps differ by {diff}"
    spent: dict[str, list[float]] = {"dyngs": [], "kornia": []}
    for round_ in range(repeats + 2):
        for name, fn in (("dyngs", ssim_map), ("kornia", theirs)):
            started = time.perf_counter()
            fn(pred, target).mean().backward()
            if round_ >= 2:  # two warm-up rounds
                spent[name].append(time.perf_counter() - started)
    medians = {name: statistics.median(times) * 1e3 for name, times in spent.items()}
    return {"height": height, "width": width, "max_diff": diff,
            **{f"{name}_ms": ms for name, ms in medians.items()}}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--sizes", nargs="+", default=["100", "128", "270x480"],
                        help="N (N×N) or HxW")  # fmt: skip
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks/results/ssim.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for size in args.sizes:
        height, _, width = size.partition("x")
        row = time_size(int(height), int(width or height), args.repeats)
        rows.append(row)
        print(f"{row['height']}×{row['width']}: dyngs {row['dyngs_ms']:.2f} ms, "
              f"kornia {row['kornia_ms']:.2f} ms (forward + backward, medians)")  # fmt: skip
    write_report(args.output, ROOT, args.threads, threads=args.threads, rows=rows)


if __name__ == "__main__":
    main()

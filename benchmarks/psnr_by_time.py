"""PSNR of evaluated runs by time: where in the sequence does a model lose?

    python benchmarks/psnr_by_time.py outputs/bench/*/points/* --split test --output FILE

Reads each run's `eval_<split>.json` (written by `dyngs-eval` or `dyngs-bench`), groups
its frames into `--bins` equal spans of t ∈ [0, 1] and prints, per run, the seed, the
mean PSNR and the mean PSNR of each span. Writes the same figures to --output (JSON).
A run that was not evaluated on the split is reported and skipped.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from statistics import mean


def by_time(frames: list[dict], bins: int) -> list[float | None]:
    """Mean PSNR of the frames in each of `bins` equal spans of t ∈ [0, 1] (None: empty)."""
    spans: list[list[float]] = [[] for _ in range(bins)]
    for frame in frames:
        spans[min(int(frame["time"] * bins), bins - 1)].append(frame["psnr"])
    return [mean(span) if span else None for span in spans]


def summarize(run_dir: Path, split: str, bins: int) -> dict | None:
    path = run_dir / f"eval_{split}.json"
    if not path.is_file():
        print(f"{run_dir}: no eval_{split}.json, skipped", file=sys.stderr)
        return None
    evaluation = json.loads(path.read_text())
    config_path = run_dir / "config.json"
    seed = json.loads(config_path.read_text()).get("seed") if config_path.is_file() else None
    return {
        "run": str(run_dir),
        "seed": seed,
        "psnr": evaluation["psnr"],
        "psnr_by_time": by_time(evaluation["frames"], bins),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--split", default="test", choices=("train", "val", "test"))
    parser.add_argument("--bins", type=int, default=5)
    parser.add_argument("--output", type=Path)
    args = parser.parse_args()
    if args.bins < 1:
        parser.error(f"--bins must be ≥ 1, got {args.bins}")

    rows = [row for run in args.runs if (row := summarize(run, args.split, args.bins))]
    edges = [f"{i / args.bins:.1f}-{(i + 1) / args.bins:.1f}" for i in range(args.bins)]
    print(f"{'run':<60} seed   PSNR  " + "  ".join(f"{e:>7}" for e in edges))
    for row in rows:
        cells = "  ".join(f"{p:7.2f}" if p is not None else "      -" for p in row["psnr_by_time"])
        print(f"{row['run'][-60:]:<60} {row['seed']!s:>4} {row['psnr']:6.2f}  {cells}")
    if args.output:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        payload = {"split": args.split, "time_spans": edges, "runs": rows}
        args.output.write_text(json.dumps(payload, indent=2) + "\n")
        print(f"wrote {args.output}")


if __name__ == "__main__":
    main()

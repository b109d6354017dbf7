"""What drawing the importance views shrunk costs and changes, on trained models.

    python benchmarks/importance_factor.py outputs/RUN --factor 2 --threads 1

Before each refinement the importance pass renders `--densify.importance-views` (100)
training views without gradient and prunes every Gaussian that never makes
`--densify.prune-importance` (0.5) pixels' worth of any of them (docs/CAPACITY.md). This
script measures that pass on a run's final model, over 100 training views spread evenly
over the whole sequence, once with the views whole and once shrunk by `--factor` (as
`--densify.importance-factor` draws them), alternating the two `--repeats` times so that
slow spells hit both alike. It reports the median seconds of each pass, how many
Gaussians each would prune, how many of those decisions differ, and how far the shrunk
measure lies from the whole one where it matters (importance between 0.25 and 4 whole
pixels). The figures go to `--output` as JSON.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from dyngs.engine.lifecycle import largest_shares
from dyngs.renderers.base import ContributionRenderer
from dyngs.runs import load_run
from dyngs.tools.common import machine_info, source_commit

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--factor", type=int, default=2)
    parser.add_argument("--views", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threshold", type=float, default=0.5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--output", type=Path, default=ROOT / "benchmarks/results/importance-factor.json"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    run = load_run(args.run)
    renderer = run.renderer
    if not isinstance(renderer, ContributionRenderer):
        raise SystemExit(f"{args.run}: its renderer does not measure contribution")
    poses = run.data().train_poses(1.0, args.views)
    background = run.scene.background.to(run.device, torch.float32)
    n = len(run.model.canonical)

    def measure(factor: int) -> tuple[torch.Tensor, float]:
        importance = torch.zeros(n, device=run.device)
        started = time.perf_counter()
        with torch.no_grad():
            shrunk = [(factor, camera, t) for camera, t in poses]
            largest_shares(run.model, renderer, shrunk, background, importance)
        return importance, time.perf_counter() - started

    seconds: dict[int, list[float]] = {1: [], args.factor: []}
    measured: dict[int, torch.Tensor] = {}
    for _ in range(args.repeats):
        for factor in (1, args.factor):
            measured[factor], took = measure(factor)
            seconds[factor].append(took)
    whole, shrunk = measured[1], measured[args.factor]
    pruned_whole, pruned_shrunk = whole < args.threshold, shrunk < args.threshold
    near = (whole > 0.25) & (whole < 4.0)
    ratio = (shrunk[near] / whole[near]).log2().abs() if bool(near.any()) else torch.zeros(1)
    report = {
        "run": str(args.run),
        "factor": args.factor,
        "views": len(poses),
        "view_size": [poses[0][0].width, poses[0][0].height],
        "gaussians": n,
        "seconds_whole": statistics.median(seconds[1]),
        "seconds_shrunk": statistics.median(seconds[args.factor]),
        "seconds_whole_all": seconds[1],
        "seconds_shrunk_all": seconds[args.factor],
        "pruned_whole": int(pruned_whole.sum()),
        "pruned_shrunk": int(pruned_shrunk.sum()),
        "pruned_only_whole": int((pruned_whole & ~pruned_shrunk).sum()),
        "pruned_only_shrunk": int((pruned_shrunk & ~pruned_whole).sum()),
        "near_threshold": int(near.sum()),
        "near_median_abs_log2_ratio": float(ratio.median()),
        "near_p90_abs_log2_ratio": float(ratio.quantile(0.9)),
        "threads": args.threads,
        "commit": source_commit(ROOT),
        "machine": machine_info(args.threads),
    }
    print(json.dumps({k: v for k, v in report.items() if k != "machine"}, indent=1))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()

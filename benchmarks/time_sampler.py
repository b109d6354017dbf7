"""Time the HexPlane field's plane sampling both ways: `grid_sample`
(`plane_sampler.reference_sample`, the definition) against the compiled sampler
(`plane_sampler.sample_group`, the default on CPUs).

    python benchmarks/time_sampler.py --threads 2 --output benchmarks/results/sampler.json

For each point count, the field alone, forward and backward at N random points and times,
the two ways interleaved round by round in one process. The grid is the demo's
data-sized one by default (35³ × 13, two scales, 32 channels; `--resolution 128 128 128
134` gives hfu-3cam's), its planes departed from their start. The demo trains with about
6 800 Gaussians, all dynamic, until its first motion split, and about 1 850 dynamic ones
after it. Medians over --repeats rounds after a warm-up; the figures go to --output as
JSON.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from time_products import interleaved_medians, perturbed_field  # noqa: E402

from dyngs.fields import hexplane, plane_sampler  # noqa: E402
from dyngs.tools.common import write_report  # noqa: E402

WAYS = {"grid_sample": plane_sampler.reference_sample, "compiled": plane_sampler.sample_group}


def time_points(
    points: int, features: int, resolution: tuple[int, ...], repeats: int
) -> dict[str, float]:
    """Median ms of the field's forward and backward at `points` points, each way."""
    generator = torch.Generator().manual_seed(0)
    field, _ = perturbed_field(resolution, features, generator)
    xyz = (2 * torch.rand(points, 3, generator=generator) - 1).requires_grad_(True)
    t = torch.rand(points, 1, generator=generator)
    upstream = torch.randn(points, field.out_dim, generator=generator)

    def use(way: str) -> None:
        hexplane.sample_group = WAYS[way]  # what the field's forward calls
        field.zero_grad(set_to_none=True)
        xyz.grad = None

    def step(_way: str) -> None:
        field(xyz, t).backward(upstream)

    try:
        return interleaved_medians(WAYS, use, step, repeats)
    finally:
        hexplane.sample_group = WAYS["compiled"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--points", type=int, nargs="+", default=[1850, 6800])
    parser.add_argument("--features", type=int, default=32)
    parser.add_argument(
        "--resolution", type=int, nargs=4, default=[35, 35, 35, 13], help="x y z t, coarsest scale"
    )
    parser.add_argument("--repeats", type=int, default=60)
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks/results/sampler.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for points in args.points:
        medians = time_points(points, args.features, tuple(args.resolution), args.repeats)
        rows.append({"features": args.features, "resolution": args.resolution, "points": points,
                     **medians})  # fmt: skip
        print(
            f"{points} points, {args.features} channels: field forward + backward "
            f"{medians['grid_sample']:.2f} ms with grid_sample, {medians['compiled']:.2f} ms "
            f"compiled ({medians['grid_sample'] / medians['compiled']:.2f}×)"
        )
    write_report(args.output, ROOT, args.threads, repeats=args.repeats, rows=rows)


if __name__ == "__main__":
    main()

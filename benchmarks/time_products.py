"""Time the HexPlane field's plane products both ways: PyTorch operations
(`hexplane.plane_products`, the reference) against the compiled pass
(`hexplane.compiled_products`, the default on CPUs).

    python benchmarks/time_products.py --threads 1 --output benchmarks/results/products.json

For each feature width, one training step's deformation work: the field at N random
points and times (the demo's data-sized grid, 35³ × 13, two scales) and the deformation
head, forward and backward, the two products interleaved round by round in one process.
Medians over --repeats rounds after a warm-up; the figures go to --output as JSON.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dyngs.fields import DeformationHeadConfig, HexPlaneConfig, hexplane  # noqa: E402
from dyngs.fields.hexplane import HexPlaneField  # noqa: E402
from dyngs.tools.common import write_report  # noqa: E402
from dyngs.types import SceneBox  # noqa: E402

WAYS = {"pytorch": hexplane.plane_products, "compiled": hexplane.compiled_products}


WARMUP = 3
"""Rounds run before timing starts."""


def perturbed_field(
    resolution: tuple[int, ...], features: int, generator: torch.Generator
) -> tuple[HexPlaneField, SceneBox]:
    """A HexPlane field over the box [-1, 1]³ whose planes have departed from their
    static start (random departures of 0.1), as after some training; and the box."""
    box = SceneBox((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    field = HexPlaneConfig(resolution=resolution, features=features).build(box, generator=generator)
    with torch.no_grad():
        for grid in field.grids:
            grid.add_(0.1 * torch.randn(grid.shape, generator=generator))
    return field, box


def interleaved_medians(
    ways: Iterable[str], prepare: Callable[[str], None], step: Callable[[str], None],
    repeats: int,
) -> dict[str, float]:  # fmt: skip
    """Median ms of `step(way)` for each way, the ways taking turns round by round (so
    that a busy spell of the machine slows them alike), over `repeats` rounds after
    `WARMUP`; `prepare(way)` runs before each timed call, outside the timing."""
    times: dict[str, list[float]] = {way: [] for way in ways}
    for round_ in range(repeats + WARMUP):
        for way, spent in times.items():
            prepare(way)
            started = time.perf_counter()
            step(way)
            if round_ >= WARMUP:
                spent.append(1e3 * (time.perf_counter() - started))
    return {way: statistics.median(spent) for way, spent in times.items()}


def time_width(features: int, points: int, repeats: int) -> dict[str, float]:
    """Median ms of the field and head forward and backward, each way."""
    generator = torch.Generator().manual_seed(0)
    field, box = perturbed_field((35, 35, 35, 13), features, generator)
    head = DeformationHeadConfig().build(field.out_dim, box, generator=generator)
    xyz = (2 * torch.rand(points, 3, generator=generator) - 1).requires_grad_(True)
    t = torch.rand(points, 1, generator=generator)

    def use(way: str) -> None:
        hexplane.compiled_products = WAYS[way]  # what the field's forward calls

    def step(_way: str) -> None:
        deltas = head(field(xyz, t))
        assert deltas.quats is not None
        (deltas.means.sum() + deltas.quats.sum()).backward()

    try:
        return interleaved_medians(WAYS, use, step, repeats)
    finally:
        hexplane.compiled_products = WAYS["compiled"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--points", type=int, default=7000, help="the demo's dynamic Gaussians")
    parser.add_argument("--features", type=int, nargs="+", default=[16, 32])
    parser.add_argument("--repeats", type=int, default=40)
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks/results/products.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for features in args.features:
        medians = time_width(features, args.points, args.repeats)
        rows.append({"features": features, "points": args.points, **medians})
        print(
            f"{features} features, {args.points} points: field and head forward + backward "
            f"{medians['pytorch']:.2f} ms with PyTorch's products, "
            f"{medians['compiled']:.2f} ms compiled"
        )
    write_report(args.output, ROOT, args.threads, repeats=args.repeats, rows=rows)


if __name__ == "__main__":
    main()

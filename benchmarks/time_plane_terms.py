"""Time a step's plane regularizers both ways: PyTorch operations on each plane's view
(`tv.plane_tv`, `temporal.time_smoothness`, `temporal.time_l1_to_static`, the reference)
against one compiled pass each way over the field's stacked groups
(`compiled_planes.plane_values`, the default on CPUs).

    python benchmarks/time_plane_terms.py --threads 1 --output FILE

For each field (the demo's data-sized grid, 35³ × 13 with 32 channels, and texture's,
25 × 25 × 35 × 18 with 16; two scales each), `objective.plane_terms` with the default
weights, forward and backward into the field's parameters, the two ways interleaved round
by round in one process. Medians over --repeats rounds after a warm-up; the figures go to
--output as JSON.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from time_products import interleaved_medians, perturbed_field  # noqa: E402

from dyngs.config import LossConfig  # noqa: E402
from dyngs.engine.objective import plane_terms  # noqa: E402
from dyngs.fields.base import PlaneGrids  # noqa: E402
from dyngs.tools.common import write_report  # noqa: E402

FIELDS = {
    "demo": ((35, 35, 35, 13), 32),
    "texture": ((25, 25, 35, 18), 16),
}


def time_field(resolution: tuple[int, ...], features: int, repeats: int) -> dict[str, float]:
    """Median ms of the default plane terms forward and backward, each way."""
    field, _ = perturbed_field(resolution, features, torch.Generator().manual_seed(0))
    weights = LossConfig()

    def step(way: str) -> None:
        grouped = field.planes()
        if way == "pytorch":  # the same planes without their groups: the reference path
            grouped = PlaneGrids(spatial=grouped.spatial, temporal=grouped.temporal)
        terms = plane_terms(weights, grouped)
        torch.stack(list(terms.values())).sum().backward()

    return interleaved_medians(("pytorch", "compiled"), lambda _way: field.zero_grad(), step,
                               repeats)  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=40)
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks/results/plane-terms.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for name, (resolution, features) in FIELDS.items():
        medians = time_field(resolution, features, args.repeats)
        rows.append({"field": name, "resolution": resolution, "features": features, **medians})
        print(
            f"{name} field {resolution}, {features} channels: plane terms forward + backward "
            f"{medians['pytorch']:.2f} ms in PyTorch, {medians['compiled']:.2f} ms compiled"
        )
    write_report(args.output, ROOT, args.threads, repeats=args.repeats, rows=rows)


if __name__ == "__main__":
    main()

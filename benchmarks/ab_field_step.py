"""Time a training step with this checkout's field sampler and plane products against
another checkout's, alternated step by step inside one training run.

    git worktree add /tmp/before HEAD~1   # or: git archive HEAD~1 | tar -x -C /tmp/before
    python benchmarks/ab_field_step.py --before /tmp/before --at 1200 --steps 60 \\
        -- hexplane-4dgs --data demo

This machine's speed drifts by up to ~2× within an hour, so two runs timed one after the
other cannot resolve a change of a few per cent. Here one run trains `--at` steps with
this checkout's code, then times `--steps` pairs of steps: one with the field's
`sample_group` and `compiled_products` from --before's `dyngs/fields` (its
`plane_sampler`, `sampler_kernels`, `product_kernels` and `hexplane`, loaded under other
names), one with this checkout's, the order flipped from pair to pair. Both ways see the
same model, within a step of each other, and the same machine. Medians of each way's step
times go to --output as JSON. Everything else in a step is this checkout's code.
`benchmarks/ab_step.py` does the same for any names; this is its A/B of the field.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))  # ab_step, also when loaded by a test

import ab_step  # noqa: E402
from profile_step import train_command  # noqa: E402

MODULES = ("plane_sampler", "sampler_kernels", "product_kernels", "hexplane")
"""The field modules taken from --before, in the order they import one another."""

SWAPS = ("dyngs.fields.hexplane:sample_group", "dyngs.fields.hexplane:compiled_products")
"""What the before steps take from --before."""


def load_before(checkout: Path, folder: Path) -> ModuleType:
    """--before's `hexplane`, with its own sampler and products (`ab_step.load_before`)."""
    modules = [f"dyngs.fields.{name}" for name in MODULES]
    return ab_step.load_before(checkout, folder, modules)["dyngs.fields.hexplane"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", type=Path, required=True, help="another checkout's root")
    parser.add_argument("--at", type=int, default=1200, help="steps trained before timing")
    parser.add_argument("--steps", type=int, default=60, help="pairs of steps timed")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--output", type=Path, default=ROOT / "benchmarks/results/ab-field-step.json"
    )
    parser.add_argument("train", nargs=argparse.REMAINDER, help="-- then a dyngs-train command")
    args = parser.parse_args()
    also = [f"dyngs.fields.{name}" for name in MODULES]
    ab_step.run(args.before, list(SWAPS), also, args.at, args.steps, args.threads, args.output,
                train_command(args.train))  # fmt: skip


if __name__ == "__main__":
    main()

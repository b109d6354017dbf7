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
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))  # profile_step, also when loaded by a test

from profile_step import train_command, trainer_at  # noqa: E402

from dyngs.fields import hexplane  # noqa: E402
from dyngs.tools.common import source_commit, write_report  # noqa: E402

MODULES = ("plane_sampler", "sampler_kernels", "product_kernels", "hexplane")
"""The field modules taken from --before, in the order they import one another."""


def load_before(checkout: Path, folder: Path) -> ModuleType:
    """--before's `hexplane`, with its own sampler and products: each module's source is
    copied into `folder` as `before_NAME`, its imports of the others pointed there."""
    for name in MODULES:
        source = (checkout / "dyngs/fields" / f"{name}.py").read_text()
        for other in MODULES:
            source = source.replace(f"from dyngs.fields import {other}",
                                    f"import before_{other} as {other}")  # fmt: skip
            source = source.replace(f"from dyngs.fields.{other} import",
                                    f"from before_{other} import")  # fmt: skip
        (folder / f"before_{name}.py").write_text(source)
    sys.path.insert(0, str(folder))
    module = None
    for name in MODULES:
        spec = importlib.util.spec_from_file_location(
            f"before_{name}", folder / f"before_{name}.py"
        )
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[f"before_{name}"] = module
        spec.loader.exec_module(module)
    assert module is not None
    return module


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
    command = train_command(args.train)
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as folder:
        before = load_before(args.before, Path(folder))
        ways = {
            "before": (before.sample_group, before.compiled_products),
            "this": (hexplane.sample_group, hexplane.compiled_products),
        }
        trainer = trainer_at(command, args.at, Path(folder))
        seconds: dict[str, list[float]] = {way: [] for way in ways}
        step = args.at
        for pair in range(args.steps + 1):
            for way in ("before", "this") if pair % 2 == 0 else ("this", "before"):
                hexplane.sample_group, hexplane.compiled_products = ways[way]
                started = time.perf_counter()
                trainer.train_step(step)
                if pair > 0:  # the first pair compiles and warms both ways
                    seconds[way].append(time.perf_counter() - started)
                step += 1
        hexplane.sample_group, hexplane.compiled_products = ways["this"]
        gaussians, dynamic = len(trainer.model.canonical), trainer.model.dynamic_fraction()
    medians = {way: statistics.median(times) * 1e3 for way, times in seconds.items()}
    print(
        f"step {args.at}: before {medians['before']:.2f} ms, this {medians['this']:.2f} ms a "
        f"step ({medians['before'] / medians['this']:.3f}×; medians of {args.steps}), "
        f"{gaussians} Gaussians, {dynamic:.0%} dynamic"
    )
    write_report(args.output, ROOT, args.threads, train=" ".join(command), at=args.at,
                 pairs=args.steps, step_ms_median=medians, gaussians=gaussians,
                 dynamic_fraction=dynamic, before=source_commit(args.before))  # fmt: skip


if __name__ == "__main__":
    main()

"""Time a training step with another checkout's version of some functions against this
checkout's, alternated step by step inside one training run.

    git archive HEAD~1 | tar -x -C /tmp/before
    python benchmarks/ab_step.py --before /tmp/before --at 3000 --steps 100 \\
        --swap dyngs.losses.photometric:ssim_map --swap dyngs.model:DynamicGaussians.at \\
        -- hexplane-4dgs --data demo

This machine's speed drifts by up to ~2× within an hour, so two runs timed one after the
other cannot resolve a change of a few per cent. Here one run trains `--at` steps with
this checkout's code, then times `--steps` pairs of steps, the order flipped from pair to
pair: in one step of each pair every `--swap MODULE:NAME` (NAME may be dotted, as in
`Class.method`) is --before's, in the other this checkout's. Both ways see the same model,
within a step of each other, and the same machine. Medians of each way's step times go to
--output as JSON.

--before's modules are loaded from its source under other names (`before_dyngs_...`): the
modules of the swaps, and those named by `--with`, whose imports of one another are pointed
at each other (give `--with` the modules a swapped function calls that differ between the
checkouts, such as its compiled kernels; list them before the modules that import them).
Every other import is this checkout's. A swap replaces NAME where it is looked up: a caller
that took it with `from MODULE import NAME` keeps this checkout's, so swap it in the
caller's module too, or swap the caller.

The copies are kept in --before's `.ab_step` folder, so that numba caches their kernels
there. A kernel can run at another speed compiled in the process than loaded from numba's
disk cache, as every run after a user's first loads it, so the first A/B of a --before
(whose copies compile) says so, and the second times both ways as users get them.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import statistics
import sys
import tempfile
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))  # profile_step, also when loaded by a test

from profile_step import train_command, trainer_at  # noqa: E402

from dyngs.tools.common import source_commit, write_report  # noqa: E402

BEFORE_FOLDER = ".ab_step"
"""Where --before's modules are copied, inside --before: kept, so that numba loads their
kernels from its disk cache from the second A/B on, as this checkout's are loaded."""


def before_name(module: str) -> str:
    """The name --before's `module` is loaded under: `dyngs.a.b` → `before_dyngs_a_b`."""
    return "before_" + module.replace(".", "_")


def load_before(checkout: Path, folder: Path, modules: list[str]) -> dict[str, ModuleType]:
    """--before's `modules` (dotted names, each after those it imports), each one's source
    copied into `folder` under `before_name`, its imports of the others pointed there. A
    copy is rewritten only when its text changes: numba's disk cache is keyed on the
    file's modification time, and it must survive from one A/B to the next."""
    for module in modules:
        source = (checkout / Path(*module.split("."))).with_suffix(".py").read_text()
        for other in modules:
            package, _, leaf = other.rpartition(".")
            source = source.replace(f"from {package} import {leaf}\n",
                                    f"import {before_name(other)} as {leaf}\n")  # fmt: skip
            source = source.replace(f"from {other} import", f"from {before_name(other)} import")
        copy = folder / f"{before_name(module)}.py"
        if not copy.exists() or copy.read_text() != source:
            copy.write_text(source)
    sys.path.insert(0, str(folder))
    loaded = {}
    for module in modules:
        name = before_name(module)
        spec = importlib.util.spec_from_file_location(name, folder / f"{name}.py")
        assert spec is not None and spec.loader is not None
        loaded[module] = importlib.util.module_from_spec(spec)
        sys.modules[name] = loaded[module]
        spec.loader.exec_module(loaded[module])
    return loaded


def compiled_here(modules: Iterable[ModuleType]) -> list[str]:
    """The compiled kernels of `modules` that numba compiled in this process rather than
    loading them from its disk cache. The two can differ in speed (numba issue #8085: a
    plane-product backward took 0.9 ms compiled in the process and 1.9 ms loaded from the
    cache, docs/TRAINING.md), so an A/B of kernels compares them loaded the same way."""
    return [
        f"{module.__name__}.{name}"
        for module in modules
        for name, value in vars(module).items()
        if sum(getattr(getattr(value, "stats", None), "cache_misses", {}).values())
    ]


@dataclass(frozen=True)
class Swap:
    """One name swapped: `owner.attribute` is `before` in the before steps, `this` in the
    others."""

    owner: Any
    attribute: str
    before: Any
    this: Any

    @classmethod
    def parse(cls, spec: str, before: dict[str, ModuleType]) -> Swap:
        """`MODULE:NAME` (NAME dotted) → the swap, from --before's loaded `MODULE`."""
        module, _, path = spec.partition(":")
        if not path:
            raise SystemExit(f"--swap {spec!r}: expected MODULE:NAME, e.g. dyngs.model:activate")
        *parents, attribute = path.split(".")
        owner, old = importlib.import_module(module), before[module]
        for part in parents:
            owner, old = getattr(owner, part), getattr(old, part)
        if isinstance(owner, type):  # the raw function, not one bound to the class
            this, old_value = owner.__dict__[attribute], old.__dict__[attribute]
        else:
            this, old_value = getattr(owner, attribute), getattr(old, attribute)
        return cls(owner, attribute, old_value, this)

    def use(self, way: str) -> None:
        setattr(self.owner, self.attribute, self.before if way == "before" else self.this)


def time_both_ways(trainer: Any, swaps: list[Swap], at: int, pairs: int) -> dict[str, float]:
    """Median step seconds each way over `pairs` pairs after one untimed pair (it compiles
    and warms both ways), the order flipped from pair to pair; this checkout's code is
    left in place whatever happens."""
    seconds: dict[str, list[float]] = {"before": [], "this": []}
    step = at
    try:
        for pair in range(pairs + 1):
            for way in ("before", "this") if pair % 2 == 0 else ("this", "before"):
                for swap in swaps:
                    swap.use(way)
                started = time.perf_counter()
                trainer.train_step(step)
                if pair > 0:
                    seconds[way].append(time.perf_counter() - started)
                step += 1
    finally:
        for swap in swaps:
            swap.use("this")
    return {way: statistics.median(times) for way, times in seconds.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", type=Path, required=True, help="another checkout's root")
    parser.add_argument("--swap", action="append", required=True, metavar="MODULE:NAME",
                        help="a name whose --before version the before steps use")  # fmt: skip
    parser.add_argument("--with", dest="also", action="append", default=[], metavar="MODULE",
                        help="another module of --before's the swapped code calls")  # fmt: skip
    parser.add_argument("--at", type=int, default=1200, help="steps trained before timing")
    parser.add_argument("--steps", type=int, default=60, help="pairs of steps timed")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks/results/ab-step.json")
    parser.add_argument("train", nargs=argparse.REMAINDER, help="-- then a dyngs-train command")
    args = parser.parse_args()
    run(args.before, args.swap, args.also, args.at, args.steps, args.threads, args.output,
        train_command(args.train))  # fmt: skip


def run(
    checkout: Path,
    swaps: list[str],
    also: list[str],
    at: int,
    pairs: int,
    threads: int,
    output: Path,
    command: list[str],
) -> dict[str, float]:
    """The A/B of `main` (also for scripts with swaps of their own); returns the median
    milliseconds a step each way."""
    torch.set_num_threads(threads)
    modules = list(dict.fromkeys([*also, *(spec.partition(":")[0] for spec in swaps)]))
    copies = checkout / BEFORE_FOLDER
    copies.mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory() as folder:
        before = load_before(checkout, copies, modules)
        chosen = [Swap.parse(spec, before) for spec in swaps]
        trainer = trainer_at(command, at, Path(folder))
        medians = {way: s * 1e3 for way, s in time_both_ways(trainer, chosen, at, pairs).items()}
        gaussians, dynamic = len(trainer.model.canonical), trainer.model.dynamic_fraction()
    if fresh := compiled_here(before.values()):
        print(
            f"note: --before's {', '.join(fresh)} compiled in this process, not loaded from "
            "numba's cache as this checkout's were; run again to time both as users get them"
        )
    print(
        f"step {at}: before {medians['before']:.2f} ms, this {medians['this']:.2f} ms a step "
        f"({medians['before'] / medians['this']:.3f}×; medians of {pairs}), "
        f"{gaussians} Gaussians, {dynamic:.0%} dynamic"
    )
    write_report(output, ROOT, threads, train=" ".join(command), at=at, pairs=pairs,
                 swaps=swaps, modules_from_before=modules, step_ms_median=medians,
                 gaussians=gaussians, dynamic_fraction=dynamic,
                 before=source_commit(checkout))  # fmt: skip
    return medians


if __name__ == "__main__":
    main()

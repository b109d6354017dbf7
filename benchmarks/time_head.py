"""Time the deformation head's forward and backward: as built, against a ReLU per branch.

    python benchmarks/time_head.py --threads 1 --rows 5000 11000

The head (`dyngs/fields/heads.py`) applies ReLU to its trunk's output once, for every
branch; until it did, each branch began with its own ReLU, computing the same activation
and its backward once per branch. This script times one forward and backward of the
default head (position, rotation and scale branches, width 64) on random features, as
built and as the per-branch reference computes it, interleaved over `--repeats` rounds,
and reports the medians. The two must give the same deltas (checked before timing). It
writes the figures to `--output` as JSON.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor, nn

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dyngs.fields import DeformationHead, DeformationHeadConfig  # noqa: E402
from dyngs.tools.common import write_report  # noqa: E402
from dyngs.types import SceneBox  # noqa: E402

BRANCHES = ("means", "quats", "scales")
"""The branches of the default head (`DeformationHeadConfig()`)."""


def build_head(features: int, generator: torch.Generator) -> DeformationHead:
    """The head with position, rotation and scale branches (the default when the figures in
    docs/RENDERER.md were measured), its last layers made non-zero (as after training)."""
    box = SceneBox((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    head = DeformationHeadConfig(scale=True).build(features, box, generator=generator)
    for name in BRANCHES:
        nn.init.normal_(getattr(head, name)[3].weight, std=0.1, generator=generator)
    return head


def as_built(head: DeformationHead, x: Tensor) -> list[Tensor]:
    deltas = head(x)
    return [deltas.means, deltas.quats, deltas.scales]


def per_branch(head: DeformationHead, x: Tensor) -> list[Tensor]:
    """The head as it was: every branch applies ReLU to the trunk's output itself."""
    hidden = head.trunk(x)
    out = []
    for name in BRANCHES:
        branch = getattr(head, name)
        out.append(branch[3](branch[2](branch[1](torch.relu(hidden)))))
    out[0] = out[0] * head.position_scale
    return out


def time_rows(rows: int, features: int, repeats: int) -> dict:
    generator = torch.Generator().manual_seed(0)
    head = build_head(features, generator)
    x = torch.randn(rows, features, generator=generator, requires_grad=True)
    variants: dict[str, Callable[[DeformationHead, Tensor], list[Tensor]]] = {
        "as_built": as_built, "per_branch": per_branch,
    }  # fmt: skip
    with torch.no_grad():
        built, reference = (f(head, x) for f in variants.values())
        for a, b in zip(built, reference, strict=True):
            if not torch.equal(a, b):
                raise SystemExit("the head as built and the per-branch reference disagree")
    seconds: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(repeats + 1):  # the first round warms up
        for name, f in variants.items():
            started = time.perf_counter()
            torch.stack([d.sum() for d in f(head, x)]).sum().backward()
            seconds[name].append(time.perf_counter() - started)
            head.zero_grad(set_to_none=True)
            x.grad = None
    ms = {name: statistics.median(s[1:]) * 1e3 for name, s in seconds.items()}
    return {"rows": rows, "features": features, "forward_backward_ms": ms,
            "saved": 1.0 - ms["as_built"] / ms["per_branch"]}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", type=int, nargs="+", default=[5000, 11000],
                        help="Gaussians the head reads (MuJoCo ~5000, demo ~11000)")  # fmt: skip
    parser.add_argument("--features", type=int, default=32, help="the field's output width")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=100)
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks/results/head.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    results = []
    for rows in args.rows:
        result = time_rows(rows, args.features, args.repeats)
        ms = result["forward_backward_ms"]
        print(f"{rows} rows: as built {ms['as_built']:.2f} ms, a ReLU per branch "
              f"{ms['per_branch']:.2f} ms ({result['saved']:.0%} saved)")  # fmt: skip
        results.append(result)
    write_report(args.output, ROOT, args.threads, repeats=args.repeats, results=results)


if __name__ == "__main__":
    main()

"""Benchmark the deformation fields: forward, and forward+backward (with and without the
deformation head), for N random points in a box, as one training step would run them.

    python benchmarks/bench_fields.py                    # 20k points, 2 threads
    python benchmarks/bench_fields.py --points 50000 --threads 1

Times are medians over --repeats runs after three warm-up runs; "cpu" is the process CPU
time, which on a shared machine tells compute from waiting. The input positions require
grad, as the canonical means do in training.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from functools import partial

import torch
from torch import Tensor

from dyngs.fields import (
    DeformationHead,
    DeformationHeadConfig,
    HexPlaneConfig,
    HexPlaneField,
    MLPField,
    MLPFieldConfig,
)
from dyngs.types import SceneBox


def measure(fn: Callable[[], None], repeats: int) -> tuple[float, float, float]:
    """Median wall, minimum wall and median CPU time of `fn`, in ms."""
    for _ in range(3):
        fn()
    wall, cpu = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w)
        cpu.append(time.process_time() - c)
    return statistics.median(wall) * 1e3, min(wall) * 1e3, statistics.median(cpu) * 1e3


def forward(field: HexPlaneField | MLPField, xyz: Tensor, t: Tensor) -> None:
    with torch.no_grad():
        field(xyz, t)


def step(
    field: HexPlaneField | MLPField,
    head: DeformationHead | None,
    xyz: Tensor,
    t: Tensor,
    params: list[Tensor],
) -> None:
    out = field(xyz, t)
    if head is None:
        loss = out.square().sum()
    else:
        d = head(out)
        loss = d.means.square().sum()
        for delta in (d.quats, d.scales):
            if delta is not None:
                loss = loss + delta.square().sum()
    loss.backward()
    for p in params:
        p.grad = None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--points", type=int, default=20_000)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    g = torch.Generator().manual_seed(0)
    box = SceneBox((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))
    xyz = (torch.rand(args.points, 3, generator=g) * 3 - 1.5).requires_grad_()
    t = torch.full((args.points, 1), 0.3)
    fields: dict[str, HexPlaneField | MLPField] = {
        "hexplane": HexPlaneConfig().build(box, generator=g),
        "mlp": MLPFieldConfig().build(box, generator=g),
    }
    print(f"N = {args.points}, {torch.get_num_threads()} threads, torch {torch.__version__}")
    for name, field in fields.items():
        head = DeformationHeadConfig().build(field.out_dim, box, generator=g)
        params = [*field.parameters(), *head.parameters(), xyz]
        runs: dict[str, Callable[[], None]] = {
            "forward": partial(forward, field, xyz, t),
            "forward+backward": partial(step, field, None, xyz, t, params),
            "with head": partial(step, field, head, xyz, t, params),
        }
        for label, fn in runs.items():
            median, low, cpu = measure(fn, args.repeats)
            print(
                f"{name:9s} {label:17s} median {median:7.1f} ms  min {low:7.1f} ms  "
                f"cpu {cpu:7.1f} ms"
            )


if __name__ == "__main__":
    main()

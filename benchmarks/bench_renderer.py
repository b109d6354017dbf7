"""Benchmark the cpu-reference renderer: forward+backward and forward-only timings and peak
memory on synthetic scenes of known size and density.

    python benchmarks/bench_renderer.py                      # the issue's targets
    python benchmarks/bench_renderer.py --sigma-px 0.75 3    # density sweep

Each configuration runs in a fresh subprocess so its peak memory is its own. The scene:
N Gaussians uniformly filling the view frustum between depths 2 and 6, random
orientations, per-axis scales log-normal (σ = 0.5) around a median projected standard
deviation of SIGMA_PX pixels, opacities uniform in [0.05, 0.95], RGB colours. The table
reports the mean depth complexity (Gaussian–pixel pairs with α ≥ 1/255 per pixel) so the
figures can be related to real scenes.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from dyngs.renderers.cpu_reference import CpuReferenceConfig
from dyngs.renderers.stages import project
from dyngs.types import Camera, Gaussians

TARGETS = [  # (N, size, forward+backward target in s)
    (10_000, 128, 0.15),
    (50_000, 256, 0.6),
    (50_000, 800, None),  # forward only is reported for this one
]


def make_scene(n: int, size: int, sigma_px: float, seed: int = 0) -> tuple[Gaussians, Camera]:
    gen = torch.Generator().manual_seed(seed)
    camera = Camera.from_fov(math.radians(60), size, size, torch.eye(4))
    z = 2 + 4 * torch.rand(n, generator=gen)
    half = torch.tensor([0.5 * size / camera.fx, 0.5 * size / camera.fy])
    xy = (torch.rand(n, 2, generator=gen) * 2 - 1) * z[:, None] * half
    means = torch.cat((xy, z[:, None]), dim=1)
    scales = (sigma_px * z / camera.fx)[:, None] * torch.exp(0.5 * torch.randn(n, 3, generator=gen))
    quats = torch.randn(n, 4, generator=gen)
    opacities = 0.05 + 0.9 * torch.rand(n, generator=gen)
    colors = torch.rand(n, 3, generator=gen)
    return Gaussians(means, quats, scales, opacities, colors), camera


def depth_complexity(gaussians: Gaussians, camera: Camera, samples: int = 4096) -> float:
    """Mean number of Gaussians per pixel with α ≥ 1/255, estimated on random pixels."""
    from dyngs.renderers.base import Guards

    screen = project(gaussians, camera, Guards())
    vis = screen.visible.nonzero().squeeze(1)
    gen = torch.Generator().manual_seed(1)
    pix = torch.rand(samples, 2, generator=gen, dtype=torch.float64)
    pix = pix * torch.tensor([camera.width, camera.height], dtype=torch.float64)
    pix = pix.floor() + 0.5
    total = 0
    for chunk in vis.split(1024):
        d = pix[None] - screen.means2d[chunk][:, None]
        a, b, c = (q[:, None] for q in screen.conics[chunk].unbind(-1))
        power = 0.5 * (a * d[..., 0] ** 2 + c * d[..., 1] ** 2) + b * d[..., 0] * d[..., 1]
        alpha = screen.opacities[chunk][:, None] * torch.exp(-power)
        total += int((alpha >= 1 / 255).sum())
    return total / samples


def run_single(
    n: int, size: int, sigma_px: float, tile_size: int | None, repeats: int, backward: bool
) -> dict:
    gaussians, camera = make_scene(n, size, sigma_px)
    renderer = CpuReferenceConfig(tile_size=tile_size).build()
    background = torch.ones(3)
    params = [
        gaussians.means,
        gaussians.quats,
        gaussians.scales,
        gaussians.opacities,
        gaussians.colors,
    ]
    baseline_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    times_fwd, times_total = [], []
    for _ in range(repeats + 1):  # the first run warms up allocators and caches
        for p in params:
            p.grad = None
            p.requires_grad_(backward)
        start = time.perf_counter()
        out = renderer(gaussians, camera, background)
        mid = time.perf_counter()
        if backward:
            (out.rgb.sum() + out.depth.sum() + out.alpha.sum()).backward()
        end = time.perf_counter()
        times_fwd.append(mid - start)
        times_total.append(end - start)
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {
        "gaussians": n,
        "size": size,
        "sigma_px": sigma_px,
        "tile_size": tile_size or "auto",
        "backward": backward,
        "repeats": repeats,
        "forward_s": statistics.median(times_fwd[1:]),
        "total_s": statistics.median(times_total[1:]),
        "peak_rss_mb": peak_kb / 1024,
        "peak_rss_increase_mb": (peak_kb - baseline_kb) / 1024,
        "depth_complexity": depth_complexity(gaussians, camera),
        "visible": int(out.visible.sum()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sigma-px", type=float, nargs="+", default=[1.5])
    parser.add_argument(
        "--tile-size", nargs="+", default=["auto"], help="tile sizes, or auto (per frame)"
    )
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--output", type=Path, default=Path("benchmarks/results/renderer.json"))
    parser.add_argument("--single", nargs=5, help=argparse.SUPPRESS)
    args = parser.parse_args()

    if args.single:  # child process: one configuration, JSON on stdout
        n, size, sigma, tile, backward = args.single
        print(
            json.dumps(
                run_single(
                    int(n),
                    int(size),
                    float(sigma),
                    None if tile == "auto" else int(tile),
                    args.repeats,
                    backward == "1",
                )
            )
        )
        return

    rows = []
    for sigma in args.sigma_px:
        for tile in args.tile_size:
            for n, size, target in TARGETS:
                backward = target is not None
                single = [str(n), str(size), str(sigma), str(tile), "1" if backward else "0"]
                cmd = [
                    sys.executable,
                    __file__,
                    "--repeats",
                    str(args.repeats),
                    "--single",
                    *single,
                ]
                result = json.loads(
                    subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
                )
                result["target_s"] = target
                rows.append(result)
                met = "" if target is None else ("met" if result["total_s"] <= target else "MISSED")
                print(
                    f"N={n:>6} {size:>4}² σ={sigma:<4} tile={tile:<2} "
                    f"{'fwd+bwd' if backward else 'fwd only'} {result['total_s']:.3f} s "
                    f"(fwd {result['forward_s']:.3f} s) peak RSS {result['peak_rss_mb']:.0f} MB "
                    f"depth complexity {result['depth_complexity']:.1f} "
                    f"{'' if target is None else f'target {target} s: {met}'}",
                    flush=True,
                )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    machine = {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
    }
    args.output.write_text(json.dumps({"machine": machine, "results": rows}, indent=2) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()

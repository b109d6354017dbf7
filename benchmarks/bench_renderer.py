"""Time cpu-tile against cpu-reference and CPU-runnable peers on identical scenes.

    python benchmarks/bench_renderer.py                                   # dyngs only
    python benchmarks/bench_renderer.py --demo-run outputs/RUN \\
        --peer splax=/path/to/venv/bin/python --peer gswarp=/path/to/venv/bin/python

Cases (the issue's): 10k Gaussians at 128² and 50k at 256², forward + backward; 50k and
200k at 800², forward; and, with `--demo-run`, a trained model's test frames (forward +
backward; SH evaluated to RGB per frame, so that every renderer does the same work).
Synthetic scenes: N Gaussians filling the view frustum between depths 2 and 6, random
orientations, log-normal scales (σ = 0.5) around a median projected standard deviation
of `--sigma-px` pixels, opacities uniform in [0.05, 0.95], RGB colours, black background.

cpu-tile's time in its compositing kernels is reported apart ("compos."); the rest of its
render is projection, binning and the PyTorch glue around them.

Every (case, renderer) runs in a fresh process (its peak memory is its own: "peak MB"
is what the process's peak RSS rose by from before the warm-up, one-off costs such as
loading compiled kernels included; "steady" what it rose by over the timed renders alone,
on Linux, where the peak can be reset after the warm-up) `--repeats` times after
`--warmup` renders (a training run renders thousands of times in one process, and cpu-tile
takes about ten renders to settle: its first few after compiling are up to 1.6× slower);
`--rounds` rounds cycle through all of them in turn, so that a
busy spell of the machine hits every renderer alike, and the medians over all rounds are
reported. On a shared machine whose pace drifts from round to round, the speed-up over
cpu-reference is also taken within each round ("× ref by round": cpu-reference's median
over the renderer's, both from that round), so that a slow round slows both sides of
its own ratio. Every renderer gets `--threads` threads. Each image is compared with
cpu-reference's (peers: the largest difference, as their rules differ in detail).

The physical limit: cpu-tile counts the Gaussian–pixel pairs it draws; each costs a
forward pass of `FORWARD_FLOPS` arithmetic operations and one exponential (backward:
`BACKWARD_FLOPS`, one exponential, one division). The cores' rates for those are measured
here (`measure_rates`: fused multiply-adds over in-cache float32 vectors, and NumPy's
vectorised float32 exp, on every thread) after every round, and the median over the
rounds is used (one measurement of a second or so moved by 2.5× between two runs on a
shared machine, docs/RENDERER.md); pairs × cost ÷ rate is the time no implementation of
this algorithm could beat on this machine.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dyngs.tools.common import keep_freed_memory, machine_info, source_commit  # noqa: E402
from dyngs.types import Camera, Gaussians  # noqa: E402

SYNTHETIC = [  # (name, Gaussians, size, backward)
    ("10k-128-fb", 10_000, 128, True),
    ("50k-256-fb", 50_000, 256, True),
    ("50k-800-f", 50_000, 800, False),
    ("200k-800-f", 200_000, 800, False),
]
DYNGS = ("cpu-tile", "cpu-reference")

FORWARD_FLOPS = 28
"""Arithmetic per drawn pair in cpu-tile's forward, counted in its kernel: the offset (2),
the exponent (9), the α clamp and floor (2), 1 − α, T(1 − α) and its test (3), the weight
(1), four multiply-adds and the α sum (9), the contribution (1); plus one exp."""
BACKWARD_FLOPS = 52
"""The same for backward: α recomputed (13), T before (1 division), the weight (1), the
upstream dot product (8), four feature gradients (8), ∂α and R (5), ∂ of the exponent with
respect to mean, conic and ln o (16); plus one exp."""


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


SCENE_ARRAYS = ("means", "quats", "scales", "opacities", "colors")
"""The Gaussians' fields a scene file holds (SH evaluated to RGB beforehand)."""


def save_scene(path: Path, gaussians: Gaussians, camera: Camera) -> None:
    """The adapters' scene file (benchmarks/peers/scene.py)."""
    k = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]])
    arrays = {name: getattr(gaussians, name).detach().float().numpy()
              for name in SCENE_ARRAYS}  # fmt: skip
    np.savez(path, **arrays, world_to_camera=camera.world_to_camera.float().numpy(),
             K=k.astype(np.float32), width=camera.width, height=camera.height)  # fmt: skip


def load_scene_file(path: Path) -> tuple[Gaussians, Camera]:
    """The Gaussians and camera of a scene file written by `save_scene`."""
    s = dict(np.load(path))
    k = s["K"].astype(np.float64)
    camera = Camera(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]),
                    torch.from_numpy(s["world_to_camera"]), int(s["width"]),
                    int(s["height"]))  # fmt: skip
    return Gaussians(**{n: torch.from_numpy(s[n]) for n in SCENE_ARRAYS}), camera


def demo_frames(run: Path, folder: Path, limit: int) -> list[Path]:
    """Up to `limit` test frames of a trained run, as scene files (SH evaluated to RGB)."""
    from dyngs.renderers.stages import prepare
    from dyngs.runs import load_run
    from dyngs.sh import eval_sh

    loaded = load_run(run)
    scene = loaded.scene
    paths = []
    views = list(zip(scene.test.cameras, scene.test.times.tolist(), strict=True))
    for index in np.linspace(0, len(views) - 1, min(limit, len(views))).round().astype(int):
        camera, t = views[index]
        with torch.no_grad():
            g = loaded.model.at(float(t))
            ready = prepare(g, camera)
            rgb = (eval_sh(g.sh_degree, g.colors[:, : (g.sh_degree + 1) ** 2],
                           ready.relative_means().float()) if g.sh_degree is not None
                   else g.colors)  # fmt: skip
        plain = Gaussians(g.means, g.quats, g.scales, g.opacities, rgb.float(), None)
        path = folder / f"demo-{index:03d}.npz"
        save_scene(path, plain, camera)
        paths.append(path)
    return paths


def run_dyngs(
    renderer: str, scene: Path, out: Path, repeats: int, backward: bool, warmup: int = 1
) -> None:
    """Child process: render `scene` with a dyngs renderer; the adapters' output format."""
    from dyngs.renderers import RENDERERS

    gaussians, camera = load_scene_file(scene)
    draw = RENDERERS.get(renderer)().build()
    composite_s = _time_compositing() if renderer == "cpu-tile" else None
    base = {n: getattr(gaussians, n) for n in SCENE_ARRAYS}
    forward_s, total_s, pairs = [], [], None
    baseline = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    steady_base: int | None = None
    for repeat in range(-warmup + 1, repeats + 1):
        leaves = {n: t.clone().requires_grad_(backward) for n, t in base.items()}
        started = time.perf_counter()
        out_ = draw(Gaussians(**leaves), camera, torch.zeros(3))
        middle = time.perf_counter()
        if backward:
            (out_.rgb.sum() + out_.alpha.sum()).backward()
        if repeat > 0:
            forward_s.append(middle - started)
            total_s.append(time.perf_counter() - started)
        elif composite_s is not None:
            composite_s.clear()  # the warm-up's
        if repeat == 0 and repeats > 0:  # the last warm-up
            del out_
            steady_base = _reset_peak_rss()
    work = getattr(draw, "last_work", None)
    if work is not None:
        pairs = int(work[:, 1].sum())
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    steady = _status_kb("VmHWM") - steady_base if steady_base is not None else math.nan
    np.save(out.with_suffix(".npy"), out_.rgb.detach().numpy())
    if composite_s is not None and backward:  # each repeat's forward and backward together
        composite_s = [a + b for a, b in zip(composite_s[0::2], composite_s[1::2], strict=True)]
    out.write_text(json.dumps({"forward_s": forward_s, "total_s": total_s, "pairs": pairs,
                               "composite_s": composite_s,
                               "peak_rss_mb": peak / 1024,
                               "peak_increase_mb": (peak - baseline) / 1024,
                               "steady_peak_increase_mb": steady / 1024}))  # fmt: skip


def _status_kb(field: str) -> int:
    """A memory figure of this process from /proc/self/status (Linux), in KiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


def _reset_peak_rss() -> int | None:
    """Reset this process's peak RSS to its current RSS (Linux: /proc/self/clear_refs)
    and return that RSS in KiB, so that the peak read later is the timed renders' own,
    without the first render's one-off costs (loading compiled kernels, first
    allocations); None where the system offers no such reset."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return _status_kb("VmRSS")
    except (OSError, KeyError):
        return None


def _time_compositing() -> list[float]:
    """Seconds spent in cpu-tile's compositing kernels, one entry per launch (forward, then
    backward): the rest of a render is projection, binning and the PyTorch glue."""
    from dyngs.renderers import cpu_tile

    spent: list[float] = []
    launch = cpu_tile._launch

    def timed(*args: object) -> None:
        started = time.perf_counter()
        launch(*args)  # type: ignore[arg-type]
        spent.append(time.perf_counter() - started)

    cpu_tile._launch = timed  # type: ignore[assignment]
    return spent


def measure_rates(threads: int, seconds: float = 0.5) -> dict[str, float]:
    """The machine's float32 multiply-add rate (operations/s, all threads) and vectorised
    float32 exp rate (per second, all threads: one core's NumPy rate × threads).

    The multiply-adds run on 256-float rows held in L1, eight dependent ones on each
    vector of a row between its load and its store, so that the vector units, not loads
    and stores, set the pace; `contract` lets LLVM fuse each multiply and add into one FMA
    but not reassociate the chain. (Written as `acc = acc * c + a` on whole arrays, as it
    first was, numba allocates a new array every round and the allocator sets the pace:
    docs/RENDERER.md, "The physical limit, corrected", says what that did to the limit.)"""
    import numba
    from numba import njit, prange

    @njit(parallel=True, fastmath={"contract"})
    def fmas(x: np.ndarray, rounds: int) -> float:  # rounds a multiple of 8
        total = 0.0
        c = np.float32(0.999)
        for t in prange(x.shape[0]):
            a = x[t]
            acc = np.zeros_like(a)
            for _ in range(rounds // 8):
                for i in range(a.shape[0]):
                    v, ai = acc[i], a[i]
                    v = v * c + ai
                    v = v * c + ai
                    v = v * c + ai
                    v = v * c + ai
                    v = v * c + ai
                    v = v * c + ai
                    v = v * c + ai
                    v = v * c + ai
                    acc[i] = v
            total += acc.sum()
        return total

    numba.set_num_threads(threads)
    rng = np.random.default_rng(0)
    x = rng.random((threads * 4, 256), dtype=np.float32)
    fmas(x, 16)
    rounds = 80000
    started = time.perf_counter()
    fmas(x, rounds)
    flops = 2 * x.size * rounds / (time.perf_counter() - started)
    y = -rng.random(4096, dtype=np.float32) * 8
    np.exp(y)
    count, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds:
        np.exp(y)
        count += y.size
    return {"flops": flops, "exps": threads * count / (time.perf_counter() - started)}


def child(kind: str, name: str, python: str, scene: Path, out: Path, args: argparse.Namespace,
          backward: bool) -> dict:  # fmt: skip
    env = dict(os.environ, THREADS=str(args.threads), OMP_NUM_THREADS=str(args.threads),
               NUMBA_NUM_THREADS=str(args.threads))  # fmt: skip
    extra = ["--backward"] if backward else []
    if kind == "dyngs":
        malloc = ["--default-malloc"] if args.default_malloc else []
        command = [sys.executable, __file__, "--child", name, str(scene), str(out),
                   "--repeats", str(args.repeats), "--warmup", str(args.warmup), *extra,
                   *malloc]  # fmt: skip
    else:
        adapter = ROOT / "benchmarks" / "peers" / f"{name}_adapter.py"
        command = [
            python,
            str(adapter),
            str(scene),
            str(out),
            "--repeats",
            str(args.repeats),
            *extra,
        ]
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else "failed"}
    result = json.loads(out.read_text())
    result["image"] = str(out.with_suffix(".npy"))
    return result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=10, help="renders before the timed ones")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--sigma-px", type=float, default=1.5)
    parser.add_argument("--demo-run", type=Path, default=None)
    parser.add_argument("--demo-frames", type=int, default=5)
    parser.add_argument(
        "--peer", action="append", default=[], help="NAME=PYTHON (an adapter in benchmarks/peers)"
    )
    parser.add_argument("--only", nargs="*", default=None, help="case names to run")
    parser.add_argument(
        "--output", type=Path, default=ROOT / "benchmarks/results/renderer-cpu-tile.json"
    )
    parser.add_argument(
        "--default-malloc", action="store_true",
        help="render with glibc's default settings, not those every dyngs tool sets "
        "(`keep_freed_memory`), to measure what they change",
    )  # fmt: skip
    parser.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    parser.add_argument("--backward", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        torch.set_num_threads(int(os.environ.get("THREADS", "2")))
        if not args.default_malloc:
            keep_freed_memory()  # as in every dyngs tool, for both renderers
        run_dyngs(
            args.child[0],
            Path(args.child[1]),
            Path(args.child[2]),
            args.repeats,
            args.backward,
            args.warmup,
        )
        return
    report(args)


def report(args: argparse.Namespace) -> None:
    work = Path(tempfile.mkdtemp(prefix="bench-renderer-"))
    cases: list[tuple[str, Path, bool]] = []
    for name, n, size, backward in SYNTHETIC:
        if args.only is None or name in args.only:
            path = work / f"{name}.npz"
            save_scene(path, *make_scene(n, size, args.sigma_px))
            cases.append((name, path, backward))
    if args.demo_run is not None and (args.only is None or "demo" in args.only):
        cases += [(p.stem, p, True) for p in demo_frames(args.demo_run, work, args.demo_frames)]
    peers = dict(p.split("=", 1) for p in args.peer)
    renderers = [("dyngs", name, sys.executable) for name in DYNGS]
    renderers += [("peer", name, python) for name, python in peers.items()]
    runs: dict[tuple[str, str], list[dict]] = {}
    rates_by_round: list[dict[str, float]] = []
    for round_ in range(args.rounds):
        for case, scene, backward in cases:
            for kind, name, python in renderers:
                out = work / f"{case}-{name}-{round_}.json"
                result = child(kind, name, python, scene, out, args, backward)
                runs.setdefault((case, name), []).append(result)
                status = (
                    result.get("error") or f"{statistics.median(result['total_s']) * 1e3:.1f} ms"
                )
                print(f"round {round_ + 1}: {case:>14} {name:>14}: {status}", flush=True)
        rates_by_round.append(measure_rates(args.threads))
    rates = {key: statistics.median(r[key] for r in rates_by_round) for key in rates_by_round[0]}
    rows = summarise(cases, renderers, runs, rates)
    print_table(rows, rates, rates_by_round)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    memory = "glibc defaults" if args.default_malloc else "keep_freed_memory"
    settings = {"repeats": args.repeats, "warmup": args.warmup, "rounds": args.rounds,
                "memory": memory}  # fmt: skip
    args.output.write_text(json.dumps({"machine": machine_info(), "commit": source_commit(ROOT),
                                       "threads": args.threads, "settings": settings,
                                       "rates": rates, "rates_by_round": rates_by_round,
                                       "rows": rows}, indent=1) + "\n")  # fmt: skip
    print(f"wrote {args.output}")


def summarise(cases: list, renderers: list, runs: dict, rates: dict) -> list[dict]:
    rows = []
    for case, _, backward in cases:
        reference = next((r for r in runs[(case, "cpu-reference")] if "image" in r), None)
        pairs = next((r["pairs"] for r in runs[(case, "cpu-tile")] if r.get("pairs")), None)
        for _, name, _ in renderers:
            good = [r for r in runs[(case, name)] if "total_s" in r]
            if not good:
                rows.append(
                    {"case": case, "renderer": name, "error": runs[(case, name)][0].get("error")}
                )
                continue
            row = {"case": case, "renderer": name, "backward": backward,
                   "forward_ms": 1e3 * statistics.median(t for r in good for t in r["forward_s"]),
                   "total_ms": 1e3 * statistics.median(t for r in good for t in r["total_s"]),
                   "peak_increase_mb": statistics.median(
                       r.get("peak_increase_mb", math.nan) for r in good),
                   "steady_peak_increase_mb": statistics.median(
                       r.get("steady_peak_increase_mb", math.nan) for r in good)}  # fmt: skip
            if reference is not None:
                diff = np.abs(np.load(good[-1]["image"]) - np.load(reference["image"]))
                row["max_diff_vs_reference"] = float(diff.max())
            composite = [t for r in good for t in (r.get("composite_s") or [])]
            if composite:
                row["composite_ms"] = 1e3 * statistics.median(composite)
            if pairs:
                cost = FORWARD_FLOPS / rates["flops"] + 1 / rates["exps"]
                if backward:
                    cost += BACKWARD_FLOPS / rates["flops"] + 1 / rates["exps"]
                row["pairs"] = pairs
                row["limit_ms"] = 1e3 * pairs * cost
            by_round = round_speedups(runs[(case, "cpu-reference")], runs[(case, name)])
            if by_round:
                row["speedup_by_round"] = by_round
            rows.append(row)
        add_speedups([r for r in rows if r["case"] == case])
    return rows


def add_speedups(rows: list[dict]) -> None:
    """Each timed row of one case gets `speedup_vs_reference`: cpu-reference's median
    total time over its own (forward + backward where the case has a backward)."""
    reference = next((r for r in rows if r["renderer"] == "cpu-reference" and "total_ms" in r),
                     None)  # fmt: skip
    for row in rows:
        if reference is not None and "total_ms" in row:
            row["speedup_vs_reference"] = reference["total_ms"] / row["total_ms"]


def round_speedups(reference: list[dict], own: list[dict]) -> list[float]:
    """cpu-reference's median total time over the renderer's, round by round (the i-th run
    of each is round i), for the rounds in which both were timed."""
    return [
        statistics.median(ref["total_s"]) / statistics.median(mine["total_s"])
        for ref, mine in zip(reference, own, strict=True)
        if "total_s" in ref and "total_s" in mine
    ]


def print_table(rows: list[dict], rates: dict, rates_by_round: list[dict] | None = None) -> None:
    flops, exps = rates["flops"] / 1e9, rates["exps"] / 1e9
    spread = ""
    if rates_by_round and len(rates_by_round) > 1:
        low, high = (f(r["flops"] for r in rates_by_round) / 1e9 for f in (min, max))
        spread = f" (median of {len(rates_by_round)} rounds, {low:.0f}-{high:.0f} GFLOP/s)"
    print(f"\nrates: {flops:.1f} GFLOP/s (float32 multiply-add), {exps:.2f} G exp/s{spread}")
    header = ("case", "renderer", "fwd ms", "total ms", "× ref", "by round", "compos.",
              "× limit", "max diff", "peak MB", "steady")  # fmt: skip
    print("{:>14} {:>14} {:>9} {:>9} {:>6} {:>11} {:>8} {:>8} {:>9} {:>8} {:>8}".format(*header))
    for r in rows:
        if "error" in r:
            print(f"{r['case']:>14} {r['renderer']:>14}  error: {r['error']}")
            continue
        ratio = r["total_ms"] / r["limit_ms"] if r.get("limit_ms") else math.nan
        diff = r.get("max_diff_vs_reference", math.nan)
        composite, peak = r.get("composite_ms", math.nan), r["peak_increase_mb"]
        steady = r.get("steady_peak_increase_mb", math.nan)
        speedup = r.get("speedup_vs_reference", math.nan)
        by_round = r.get("speedup_by_round") or [math.nan]
        rounds = f"{min(by_round):.1f}-{max(by_round):.1f}"
        print(f"{r['case']:>14} {r['renderer']:>14} {r['forward_ms']:9.1f} {r['total_ms']:9.1f} "
              f"{speedup:6.1f} {rounds:>11} {composite:8.1f} {ratio:8.1f} {diff:9.2g} "
              f"{peak:8.0f} {steady:8.0f}")  # fmt: skip


if __name__ == "__main__":
    main()

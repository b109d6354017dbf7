"""Train every scene with its default command and tabulate what it reaches.

    python benchmarks/bench_accuracy.py                     # every scene, seed 0
    python benchmarks/bench_accuracy.py --seeds 0 1 2 --only mujoco-collision
    python benchmarks/bench_accuracy.py --jobs 2 --threads 1 --time-budget 10 \
        --seeds 0 1 2 --seeded mujoco-collision     # what docs/ACCURACY.md quotes

Scenes: the built-in demo (`--data demo`), lego-tiny (`@configs/lego-tiny.args`), every
MuJoCo scene in ../shared/data (`@configs/mujoco.args`) and hfu-3cam as it comes (`--data`
alone). Each run is `dyngs-train hexplane-4dgs <args> --seed S` on `--threads` threads, `--jobs`
runs side by side (`--jobs 2 --threads 1` on two cores: train times are then those of one
core, an upper bound on an idle two-core machine's), with LPIPS weights from
../shared/weights when present. Runs already in `--output-dir` are reused. hfu-3cam's
default schedule (about 21 000 steps at 480×270) takes hours on a CPU, so it is given
`--time-budget` minutes (`--hfu-minutes`), which the run fits its schedule into;
`--time-budget M` does the same for every other scene. `--flags` adds dyngs-train flags to
every run: train a variant into its own `--output-dir` and compare it with the defaults'
runs, pair by pair, with `benchmarks/compare_runs.py`.
Writes `benchmarks/results/accuracy.json` (every run) and prints a Markdown table of
test PSNR, SSIM, LPIPS, train time, Gaussians and model size per scene (mean over seeds),
with the commit and machine, for docs/ACCURACY.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dyngs.tools.common import machine_info, source_commit  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
WEIGHTS = ROOT.parent / "shared" / "weights" / "torch-home"


def scenes(hfu_minutes: float, minutes: float | None) -> dict[str, list[str]]:
    """Scene name → its default arguments (those whose data is present), with
    `--time-budget minutes` when given."""
    budget = [] if minutes is None else ["--time-budget", str(minutes)]
    found = {"demo": ["--data", "demo", *budget]}
    if (DATA / "lego-tiny").is_dir():
        found["lego-tiny"] = ["@configs/lego-tiny.args", *budget]
    for folder in sorted(DATA.glob("mujoco-*")):
        found[folder.name] = ["@configs/mujoco.args", "--data", str(folder), *budget]
    if (DATA / "hfu-3cam").is_dir():
        found["hfu-3cam"] = ["--data", str(DATA / "hfu-3cam"), "--time-budget", str(hfu_minutes)]
    return found


def train(name: str, args: list[str], seed: int, out: Path, threads: int) -> dict:
    run = out / f"{name}-s{seed}"
    metrics = run / "metrics.json"
    if not metrics.is_file():
        env = dict(os.environ, OMP_NUM_THREADS=str(threads), NUMBA_NUM_THREADS=str(threads))
        if WEIGHTS.is_dir():
            env["TORCH_HOME"] = str(WEIGHTS)
        command = [sys.executable, "-m", "dyngs.cli", "hexplane-4dgs", *args, "--seed", str(seed),
                   "--output-dir", str(out), "--run-name", run.name]  # fmt: skip
        started = time.perf_counter()
        with open(out / f"{run.name}.log", "w") as log:
            done = subprocess.run(command, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
        if done.returncode != 0:
            return {"scene": name, "seed": seed, "error": f"exit {done.returncode}, see {log.name}"}
        print(f"{name} seed {seed}: {time.perf_counter() - started:.0f} s", flush=True)
    m = json.loads(metrics.read_text())
    keys = ("psnr", "ssim", "lpips", "train_seconds", "num_gaussians", "model_bytes",
            "dynamic_fraction", "iterations", "num_frames")  # fmt: skip
    return {"scene": name, "seed": seed, **{k: m.get(k) for k in keys}}


def table(rows: list[dict]) -> str:
    lines = [
        "| scene | seeds | test PSNR | SSIM | LPIPS | train s | steps | Gaussians | model MiB |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        runs = [r for r in rows if r["scene"] == scene and "error" not in r]
        if not runs:
            lines.append(f"| {scene} | failed | | | | | | | |")
            continue

        def mean(key: str, digits: int, runs: list[dict] = runs) -> str:
            values = [r[key] for r in runs if r.get(key) is not None]
            if not values:
                return "—"
            text = f"{statistics.mean(values):.{digits}f}"
            if len(values) > 1 and key == "psnr":
                text += f" ± {statistics.stdev(values):.2f}"
            return text

        mib = statistics.mean(r["model_bytes"] for r in runs) / 2**20
        lines.append(
            f"| {scene} | {len(runs)} | {mean('psnr', 2)} | {mean('ssim', 3)} | "
            f"{mean('lpips', 3)} | {mean('train_seconds', 0)} | {mean('iterations', 0)} | "
            f"{mean('num_gaussians', 0)} | {mib:.2f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--only", nargs="*", default=None, help="scene names")
    parser.add_argument(
        "--seeded",
        nargs="*",
        default=None,
        help="scenes that run every seed (default: all; others: the first)",
    )
    parser.add_argument("--threads", type=int, default=2, help="threads per run")
    parser.add_argument("--jobs", type=int, default=1, help="runs side by side")
    parser.add_argument("--hfu-minutes", type=float, default=20.0)
    parser.add_argument("--time-budget", type=float, default=None,
                        help="minutes for every other scene (default: none)")  # fmt: skip
    parser.add_argument("--flags", default="",
                        help='dyngs-train flags for every run, one string, e.g. '
                             '"--losses.plane-roughness 1e-3"')  # fmt: skip
    parser.add_argument("--output-dir", type=Path, default=ROOT / "outputs" / "bench-accuracy")
    parser.add_argument("--results", type=Path, default=ROOT / "benchmarks/results/accuracy.json")
    args = parser.parse_args()
    args.output_dir.mkdir(parents=True, exist_ok=True)
    flags = shlex.split(args.flags)
    chosen = {n: [*a, *flags] for n, a in scenes(args.hfu_minutes, args.time_budget).items()
              if args.only is None or n in args.only}  # fmt: skip
    seeded = set(chosen if args.seeded is None else args.seeded)
    work = [
        (n, a, s)
        for n, a in chosen.items()
        for s in args.seeds
        if s == args.seeds[0] or n in seeded
    ]
    with ThreadPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(lambda job: train(*job, args.output_dir, args.threads), work))
    commit = source_commit(ROOT)
    args.results.parent.mkdir(parents=True, exist_ok=True)
    summary = {"commit": commit, "machine": machine_info(), "threads": args.threads,
               "jobs": args.jobs, "time_budget": args.time_budget,
               "hfu_minutes": args.hfu_minutes, "flags": flags, "runs": rows}  # fmt: skip
    args.results.write_text(json.dumps(summary, indent=1) + "\n")
    print(f"\ncommit {commit}, {machine_info()}\n")
    print(table(rows))


if __name__ == "__main__":
    main()

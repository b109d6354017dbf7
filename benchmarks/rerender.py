"""Re-time trained runs: render and deformation time per frame, several times each.

    python benchmarks/rerender.py outputs/bench/adaptive-demo/points/* --repeats 5

A single evaluation's render time swings by tens of per cent on a shared machine (two
runs of the same model have differed by 1.7×). This script evaluates every run folder
`--repeats` times, each time in a fresh `dyngs-eval` process, interleaving the runs
(A, B, A, B, …) so that slow spells hit them alike, and reports the median over the
repeats of each evaluation's median frame time. Quality metrics are not re-reported:
they do not change between evaluations. `--tile-size auto 8` times every run with each
cpu-reference tile size as well (the image does not depend on it), and `--code
before=/tmp/old-checkout after=.` with each version of dyngs (each evaluation runs with
that checkout first on PYTHONPATH), so that a speed change is measured within one
session of the machine rather than across two. `--threads 1` times on one core: two
threads share the machine's two cores with whatever else runs, and their times drifted
by 30-50 % between sessions (docs/CAPACITY.md).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from dyngs.tools.common import machine_info


def with_tile_size(run: Path, tile_size: str, scratch: Path) -> Path:
    """A copy of the run folder (its checkpoint linked) whose cpu-reference renderer uses
    `tile_size` ("auto": the renderer's per-frame choice): runs trained before a renderer
    change record the tile size they were trained with, and the image does not depend
    on it."""
    copy = scratch / f"{run.name}-tile-{tile_size}"
    if not copy.is_dir():
        copy.mkdir(parents=True)
        config = json.loads((run / "config.json").read_text())
        if not config["renderer"]["__class__"].endswith(":CpuReferenceConfig"):
            raise SystemExit(f"{run}: --tile-size applies to the cpu-reference renderer only")
        config["renderer"]["tile_size"] = None if tile_size == "auto" else int(tile_size)
        (copy / "config.json").write_text(json.dumps(config))
        (copy / "checkpoint.pt").symlink_to((run / "checkpoint.pt").resolve())
    return copy


def evaluate_once(
    run: Path, split: str, output: Path, code: Path | None = None, threads: int | None = None
) -> dict[str, Any]:
    command = [
        sys.executable, "-m", "dyngs.tools.eval", "--load-dir", str(run), "--split", split,
        "--output", str(output), "--no-save-images",
    ]  # fmt: skip
    env = dict(os.environ)
    if code is not None:
        env["PYTHONPATH"] = os.pathsep.join(
            filter(None, (str(code.resolve()), env.get("PYTHONPATH")))
        )
    if threads is not None:
        env["OMP_NUM_THREADS"] = str(threads)  # PyTorch's CPU thread pool reads it at start
    subprocess.run(command, check=True, capture_output=True, env=env)
    result = json.loads(output.read_text())
    times = {key: float(result[key]) for key in ("render_ms_median", "deformation_ms")}
    # Checkouts older than the field do not report it (None: unknown).
    return times | {"cpu_threads": result.get("cpu_threads")}


def parse_codes(items: list[str]) -> dict[str, Path | None]:
    """--code LABEL=PATH items as {label: checkout}; none: the installed dyngs."""
    if not items:
        return {"installed": None}
    codes: dict[str, Path | None] = {}
    for item in items:
        label, sep, path = item.partition("=")
        if not sep or not label or not (Path(path) / "dyngs" / "__init__.py").is_file():
            raise SystemExit(f"--code {item!r}: expected LABEL=PATH, PATH a dyngs checkout")
        if label in codes:
            raise SystemExit(f"--code {item!r}: label {label!r} given twice")
        codes[label] = Path(path)
    return codes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", type=Path, nargs="+", help="run folders (config + checkpoint)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--split", default="test")
    parser.add_argument("--output", type=Path, default=Path("benchmarks/results/rerender.json"))
    parser.add_argument(
        "--tile-size",
        nargs="+",
        default=["as-trained"],
        help="cpu-reference tile sizes to re-time each run with (N, auto or as-trained); "
        "every run is timed with each, interleaved",
    )
    parser.add_argument(
        "--code",
        nargs="+",
        default=[],
        metavar="LABEL=PATH",
        help="versions of dyngs to time every run with, interleaved: a checkout (e.g. a "
        "`git worktree`) put first on PYTHONPATH; default: the installed one",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="CPU threads each evaluation may use (default: PyTorch's choice). One thread "
        "does not race the machine's other work for a second core, so its times drift less "
        "between sessions",
    )
    args = parser.parse_args()
    codes = parse_codes(args.code)
    if args.threads is not None and args.threads < 1:
        raise SystemExit(f"--threads must be ≥ 1, got {args.threads}")

    cases = [(run, tile, code) for run in args.runs for tile in args.tile_size for code in codes]
    samples: dict[tuple[Path, str, str], list[dict[str, Any]]] = {case: [] for case in cases}
    with tempfile.TemporaryDirectory() as scratch:
        for repeat in range(args.repeats):
            for i, (run, tile, code) in enumerate(cases):
                out = Path(scratch) / f"{i}_{repeat}.json"
                folder = run if tile == "as-trained" else with_tile_size(run, tile, Path(scratch))
                samples[run, tile, code].append(
                    evaluate_once(folder, args.split, out, codes[code], args.threads)
                )
                print(f"repeat {repeat + 1}/{args.repeats}  {run} (tile {tile}, code {code})  "
                      f"{samples[run, tile, code][-1]}", flush=True)  # fmt: skip

    rows = []
    for (run, tile, code), values in samples.items():
        row = {
            "run": str(run),
            "tile_size": tile,
            "code": code,
            "repeats": len(values),
            "render_ms_median": statistics.median(v["render_ms_median"] for v in values),
            "render_ms_spread": [min(v["render_ms_median"] for v in values),
                                 max(v["render_ms_median"] for v in values)],
            "deformation_ms": statistics.median(v["deformation_ms"] for v in values),
            "cpu_threads": values[0]["cpu_threads"],
        }  # fmt: skip
        rows.append(row)
        print(
            f"{run} (tile {tile}, code {code}): render {row['render_ms_median']:.1f} ms "
            f"(spread {row['render_ms_spread'][0]:.1f}-{row['render_ms_spread'][1]:.1f}), "
            f"deformation {row['deformation_ms']:.2f} ms"
        )
    machine = machine_info(args.threads)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps({"machine": machine, "results": rows}, indent=2) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()

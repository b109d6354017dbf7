"""Steps per second and peak memory per rank of data-parallel training, P = 1 and 2.

    python benchmarks/bench_distributed.py --steps 200 --repeats 3

Trains `dyngs-train hexplane-4dgs --data demo --batch-views 2 --max-iters STEPS` with
one process, then with two (gloo, started as torchrun starts them), one thread each
(OMP_NUM_THREADS=1), alternating P run by run so that a machine busy with other work
slows both alike. Each rank reports its peak resident memory (ru_maxrss) when it exits;
steps per second are the run's iterations over its `train_seconds` (training steps only:
not loading, not the evaluation). Prints the medians and writes every run, the medians,
the command, the commit and the machine to `--output`.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dyngs.tools.common import machine_info, source_commit  # noqa: E402

# Each rank runs dyngs-train and, at exit, writes its peak RSS beside the run.
RANK_MAIN = """
import atexit, json, os, resource, runpy, sys
def report():
    path = os.path.join(os.environ["BENCH_DIR"], "rss-" + os.environ.get("RANK", "0") + ".json")
    with open(path, "w") as f:
        json.dump({"peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}, f)
atexit.register(report)
sys.argv = ["dyngs-train", *sys.argv[1:]]
runpy.run_module("dyngs.cli", run_name="__main__")
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def train(processes: int, args: list[str], folder: Path) -> dict[str, object]:
    """One run with `processes` ranks; its steps per second and each rank's peak RSS."""
    port = _free_port()
    ranks = []
    for rank in range(processes):
        env = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1",
               "BENCH_DIR": str(folder)}  # fmt: skip
        if processes > 1:
            env |= {"RANK": str(rank), "LOCAL_RANK": str(rank), "WORLD_SIZE": str(processes),
                    "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)}  # fmt: skip
        command = [sys.executable, "-c", RANK_MAIN, *args]
        ranks.append(subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL))  # fmt: skip
    if any(r.wait() != 0 for r in ranks):
        raise SystemExit(f"a run with {processes} processes failed: {args}")
    metrics = json.loads((folder / "run" / "metrics.json").read_text())
    rss = [json.loads((folder / f"rss-{r}.json").read_text())["peak_rss_mib"] for r in
           range(processes)]  # fmt: skip
    return {
        "processes": processes,
        "steps_per_second": metrics["iterations"] / metrics["train_seconds"],
        "train_seconds": metrics["train_seconds"],
        "peak_rss_mib": rss,
        "psnr": metrics["psnr"],
        "num_gaussians": metrics["num_gaussians"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--batch-views", type=int, default=2)
    parser.add_argument("--data", default="demo")
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks/results/distributed.json")
    options = parser.parse_args()
    runs: list[dict[str, object]] = []
    for repeat in range(options.repeats):
        for processes in (1, 2):
            with tempfile.TemporaryDirectory() as tmp:
                args = ["hexplane-4dgs", "--data", options.data, "--output-dir", tmp,
                        "--run-name", "run", "--max-iters", str(options.steps),
                        "--batch-views", str(options.batch_views), "--no-tensorboard"]  # fmt: skip
                run = train(processes, args, Path(tmp)) | {"repeat": repeat}
            print(json.dumps(run), flush=True)
            runs.append(run)
    medians = {}
    for processes in (1, 2):
        mine = [r for r in runs if r["processes"] == processes]
        medians[f"P={processes}"] = {
            "steps_per_second": statistics.median(float(r["steps_per_second"]) for r in mine),
            "peak_rss_mib_per_rank": [
                statistics.median(float(r["peak_rss_mib"][k]) for r in mine)  # type: ignore[index]
                for k in range(processes)
            ],
        }
    commit = source_commit(ROOT)
    result = {
        "command": "python " + " ".join(sys.argv),
        "train_command": f"dyngs-train hexplane-4dgs --data {options.data} --max-iters "
        f"{options.steps} --batch-views {options.batch_views} --no-tensorboard",
        "commit": commit,
        "machine": machine_info(threads=1),
        "medians": medians,
        "runs": runs,
    }
    options.output.parent.mkdir(parents=True, exist_ok=True)
    options.output.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(medians, indent=2))


if __name__ == "__main__":
    main()

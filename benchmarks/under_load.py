"""Run a command with busy processes beside it, as on a shared machine.

    python benchmarks/under_load.py --busy 4 -- python -m pytest -q

Each busy process spins on arithmetic until the command ends (pure Python, one core
each, no memory to speak of). Prints the command's wall time and exit code and writes
them, with the machine, to `--output` (JSON). The command's own output passes through.
Tests must pass like this: none may depend on how busy the machine is.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dyngs.tools.common import machine_info  # noqa: E402


def spin(stop: multiprocessing.synchronize.Event) -> None:  # type: ignore[name-defined]
    x = 1.0
    while not stop.is_set():
        for _ in range(100_000):
            x = x * 1.0000001 + 1e-9
    print(x if x < 0 else "", end="")  # keep the loop from being optimised away


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--busy", type=int, default=4, help="busy processes beside the command")
    parser.add_argument("--output", type=Path, default=None, help="JSON file for the result")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- COMMAND ARGS…")
    args = parser.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("give the command after --")
    stop = multiprocessing.Event()
    workers = [multiprocessing.Process(target=spin, args=(stop,)) for _ in range(args.busy)]
    for worker in workers:
        worker.start()
    started = time.perf_counter()
    try:
        code = subprocess.call(command)
    finally:
        stop.set()
        for worker in workers:
            worker.join()
    seconds = time.perf_counter() - started
    result = {
        "command": command,
        "busy_processes": args.busy,
        "exit_code": code,
        "wall_seconds": round(seconds, 1),
        "machine": machine_info(),
        "date": time.strftime("%Y-%m-%d"),
    }
    print(f"exit {code} after {seconds:.0f} s with {args.busy} busy processes beside it")
    if args.output is not None:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(result, indent=2) + "\n")
    sys.exit(code)


if __name__ == "__main__":
    main()

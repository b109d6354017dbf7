"""Count the hard cases and bad inputs the test suite tries (issue 5, docs/NUMERICS.md).

    python benchmarks/count_hard_cases.py

Hard cases are the tests in the three hard-case files and the property test, counted as
pytest collects them (one per parametrisation; tests for a renderer this machine lacks are
collected, and skipped when run). Bad inputs are the broken dataset folders of the D-NeRF
corpus, the bad command-line values, and the non-finite Gaussian parameters the renderer
tests feed in. Nothing is run: the numbers come from collection and from the tests' own
case lists, so they follow the tests as they change.
"""

from __future__ import annotations

import subprocess
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HARD_CASE_FILES = {
    "renderers": "tests/renderers/test_hard_cases.py",
    "fields": "tests/fields/test_hard_cases.py",
    "losses": "tests/losses/test_hard_cases.py",
}
PROPERTY_FILE = "tests/renderers/test_properties.py"
CLI_FILE = "tests/test_cli.py"
CLI_BAD_VALUE_TESTS = ("test_bad_values_end_in_one_line", "test_unknown_renderer_is_refused")
RENDERER_SETUPS = ("cpu-reference-float64", "cpu-reference-float32", "cuda-tile-float32")


def collect(files: list[str]) -> list[str]:
    """Node ids pytest collects from `files`, without running anything."""
    command = [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider"]
    result = subprocess.run(
        [*command, *files], cwd=ROOT, capture_output=True, text=True, check=False
    )
    if result.returncode != 0:
        raise SystemExit(f"pytest could not collect {files}:\n{result.stdout}{result.stderr}")
    return [line.strip() for line in result.stdout.splitlines() if "::" in line]


def function_name(node_id: str) -> str:
    return node_id.split("::", 1)[1].split("[", 1)[0]


def main() -> None:
    sys.path.insert(0, str(ROOT))
    from tests.datamanagers.test_dnerf_bad_input import CASES
    from tests.renderers.test_hard_cases import BAD_PLACES
    from tests.renderers.test_properties import MAX_EXAMPLES, RENDERERS

    ids = collect([*HARD_CASE_FILES.values(), PROPERTY_FILE, CLI_FILE])

    def in_file(path: str) -> list[str]:
        return [i for i in ids if i.startswith(path + "::")]

    print("Hard cases (tests as collected; named cases = distinct test functions)")
    total_tests = 0
    for area, path in HARD_CASE_FILES.items():
        tests = in_file(path)
        named = len({function_name(i) for i in tests})
        total_tests += len(tests)
        print(f"  {area:<10} {len(tests):4d} tests, {named:3d} named cases   {path}")
        if area == "renderers":
            per_setup = Counter(s for i in tests for s in RENDERER_SETUPS if f"[{s}" in i)
            single = len(tests) - sum(per_setup.values())
            for setup in RENDERER_SETUPS:
                print(f"  {'':<10} {per_setup[setup]:4d} on {setup}")
            print(f"  {'':<10} {single:4d} on cpu-reference alone")
    properties = in_file(PROPERTY_FILE)
    total_tests += len(properties)
    scenes = MAX_EXAMPLES * len(RENDERERS)
    print(
        f"  {'property':<10} {len(properties):4d} test{'s' * (len(properties) != 1)}, drawing "
        f"{MAX_EXAMPLES} random scenes per renderer ({scenes} on this machine)   {PROPERTY_FILE}"
    )
    print(f"  total      {total_tests:4d} hard-case tests")

    cli = [i for i in in_file(CLI_FILE) if function_name(i) in CLI_BAD_VALUE_TESTS]
    nonfinite = 3 * len(BAD_PLACES)  # NaN, +Inf and −Inf, each in every place
    bad_total = len(CASES) + len(cli) + nonfinite
    print("Bad inputs")
    print(f"  {len(CASES):4d} broken D-NeRF folders   tests/datamanagers/test_dnerf_bad_input.py")
    print(f"  {len(cli):4d} bad command-line values   {CLI_FILE}")
    print(
        f"  {nonfinite:4d} non-finite Gaussian parameters (NaN, +Inf, −Inf in "
        f"{len(BAD_PLACES)} places)   {HARD_CASE_FILES['renderers']}"
    )
    print(f"  total {bad_total:4d} bad inputs")


if __name__ == "__main__":
    main()

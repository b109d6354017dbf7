"""benchmarks/time_plane_terms.py: it times the plane regularizers both ways, on every
field it names."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.tools.conftest import load_benchmark, run_benchmark_main

pytest.importorskip("numba")


def test_both_ways_are_timed_for_every_field(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    time_plane_terms = load_benchmark("time_plane_terms")
    output = tmp_path / "plane-terms.json"
    run_benchmark_main(time_plane_terms, ["--repeats", "1", "--output", str(output)], monkeypatch)
    report = json.loads(output.read_text())
    assert [row["field"] for row in report["rows"]] == list(time_plane_terms.FIELDS)
    for row in report["rows"]:
        assert row["pytorch"] > 0 and row["compiled"] > 0

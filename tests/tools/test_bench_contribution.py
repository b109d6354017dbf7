"""benchmarks/bench_contribution.py: times renders with and without the contribution
measure, for training steps and for evaluation."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.tools.conftest import load_benchmark, run_benchmark_main

bench = load_benchmark("bench_contribution")


def test_both_renders_are_timed_for_each_run(
    tiny_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    output = tmp_path / "contribution.json"
    argv = [str(tiny_run), "--repeats", "2", "--views", "2", "--threads", "1",
            "--output", str(output)]  # fmt: skip
    run_benchmark_main(bench, argv, monkeypatch)
    result = json.loads(output.read_text())
    assert result["machine"]["threads"] == 1
    [row] = result["results"]
    assert row["run"] == str(tiny_run) and row["views"] == 2
    for name in ("train_step", "forward"):
        cell = row[name]
        assert cell["with_contribution_ms"] > 0 and cell["without_ms"] > 0
        assert cell["saving"] == pytest.approx(
            1 - cell["without_ms"] / cell["with_contribution_ms"]
        )

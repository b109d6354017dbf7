"""benchmarks/time_products.py: it times both products and leaves the field's default as
it found it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dyngs.fields import hexplane
from tests.tools.conftest import load_benchmark, run_benchmark_main


def test_both_products_are_timed_and_the_default_restored(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    time_products = load_benchmark("time_products")
    output = tmp_path / "products.json"
    argv = ["--points", "50", "--features", "4", "--repeats", "2", "--output", str(output)]
    run_benchmark_main(time_products, argv, monkeypatch)
    assert time_products.hexplane.compiled_products is hexplane.compiled_products
    assert hexplane.compiled_products is time_products.WAYS["compiled"]
    report = json.loads(output.read_text())
    (row,) = report["rows"]
    assert row["features"] == 4 and row["points"] == 50
    assert row["pytorch"] > 0 and row["compiled"] > 0

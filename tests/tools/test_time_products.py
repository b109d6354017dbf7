"""benchmarks/time_products.py: it times both products and leaves the field's default as
it found it."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

from dyngs.fields import hexplane
from tests.tools.conftest import load_benchmark


def test_both_products_are_timed_and_the_default_restored(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    time_products = load_benchmark("time_products")
    output = tmp_path / "products.json"
    argv = ["time_products.py", "--points", "50", "--features", "4", "--repeats", "2",
            "--output", str(output)]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    threads = torch.get_num_threads()
    try:
        time_products.main()
    finally:
        torch.set_num_threads(threads)
    assert time_products.hexplane.compiled_products is hexplane.compiled_products
    assert hexplane.compiled_products is time_products.WAYS["compiled"]
    report = json.loads(output.read_text())
    (row,) = report["rows"]
    assert row["features"] == 4 and row["points"] == 50
    assert row["pytorch"] > 0 and row["compiled"] > 0

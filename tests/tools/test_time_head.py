"""benchmarks/time_head.py: the head as built against its per-branch reference."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from tests.tools.conftest import load_benchmark, run_benchmark_main


def test_the_reference_is_the_head_and_the_report_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    time_head = load_benchmark("time_head")
    generator = torch.Generator().manual_seed(1)
    head = time_head.build_head(8, generator)
    x = torch.randn(50, 8, generator=generator)
    for a, b in zip(time_head.as_built(head, x), time_head.per_branch(head, x), strict=True):
        assert torch.equal(a, b) and bool(a.abs().sum() > 0)

    output = tmp_path / "head.json"
    argv = ["--rows", "40", "--features", "8", "--repeats", "2", "--output", str(output)]
    run_benchmark_main(time_head, argv, monkeypatch)
    report = json.loads(output.read_text())
    (result,) = report["results"]
    assert result["rows"] == 40 and result["features"] == 8
    assert set(result["forward_backward_ms"]) == {"as_built", "per_branch"}
    assert all(ms > 0 for ms in result["forward_backward_ms"].values())

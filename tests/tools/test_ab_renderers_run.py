"""benchmarks/ab_renderers_run.py: two runs stepped in turn train as they would alone, and
the report holds both runs' training seconds, their ratio and their test PSNR."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch
from rich.console import Console

from tests.tools.conftest import load_benchmark, run_benchmark_main

pytest.importorskip("numba")

COMMAND = ["hexplane-4dgs", "--data", "demo", "--max-iters", "4", "--seed", "3"]


def test_both_runs_are_timed_and_evaluated(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sys, "path", list(sys.path))
    script = load_benchmark("ab_renderers_run")
    output = tmp_path / "ab.json"
    argv = ["--threads", "1", "--output", str(output), "--", *COMMAND]
    run_benchmark_main(script, argv, monkeypatch)
    report = json.loads(output.read_text())
    assert report["renderers"] == ["cpu-tile", "cpu-reference"] and report["steps"] == 4
    tile, reference = (report["train_seconds"][name] for name in report["renderers"])
    assert tile > 0 and reference > 0
    assert report["ratio"] == pytest.approx(reference / tile)
    for name in report["renderers"]:
        assert 0 < report["test"][name]["psnr"] < 100


def test_a_run_stepped_in_turn_trains_as_it_would_alone(tmp_path: Path) -> None:
    """Each trainer draws from its own generators: alternating with another run leaves its
    model as training it alone does, to the bit."""
    script = load_benchmark("ab_renderers_run")
    alone = script.trainer(COMMAND, "cpu-tile", tmp_path / "alone")
    for step in range(alone.config.steps):
        alone.train_step(step)
    paired = {
        name: script.trainer(COMMAND, name, tmp_path) for name in ("cpu-tile", "cpu-reference")
    }
    script.alternate(paired, Console(quiet=True))
    together = dict(paired["cpu-tile"].model.named_parameters())
    for name, parameter in alone.model.named_parameters():
        assert torch.equal(parameter, together[name]), name

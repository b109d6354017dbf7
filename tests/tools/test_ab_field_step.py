"""benchmarks/ab_field_step.py: another checkout's field modules load beside this one's,
under their own names, and compute what this checkout's compute; the run times both ways
and leaves the field's functions as it found them."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import ModuleType

import pytest
import torch

from dyngs.fields import hexplane
from tests.tools.conftest import load_benchmark, modules_checkout, run_benchmark_main

ROOT = Path(__file__).resolve().parents[2]

pytest.importorskip("numba")


@pytest.fixture
def ab(monkeypatch: pytest.MonkeyPatch) -> ModuleType:
    """The script as a module; the paths and `before_*` modules it adds are undone after."""
    monkeypatch.setattr(sys, "path", list(sys.path))
    script = load_benchmark("ab_field_step")
    for name in script.MODULES:
        monkeypatch.delitem(sys.modules, f"before_dyngs_fields_{name}", raising=False)
    return script


def test_the_other_checkouts_modules_load_under_their_own_names(
    ab: ModuleType, tmp_path: Path
) -> None:
    before = ab.load_before(ROOT, tmp_path)  # this checkout, as the one to compare with
    assert before.__name__ == "before_dyngs_fields_hexplane"
    assert before.sample_group is not hexplane.sample_group
    assert sys.modules["before_dyngs_fields_plane_sampler"].sample_group is before.sample_group
    generator = torch.Generator().manual_seed(0)
    planes = torch.randn(3, 8, 6, 7, generator=generator)
    coords = torch.rand(40, 4, generator=generator) * 2 - 1
    columns = torch.tensor([0, 1, 0, 2, 1, 2])
    assert torch.equal(
        before.sample_group(planes, coords, columns, 0.0),
        hexplane.sample_group(planes, coords, columns, 0.0),
    )


def test_both_ways_are_timed_and_the_field_restored(
    ab: ModuleType, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    sample_group, compiled_products = hexplane.sample_group, hexplane.compiled_products
    output = tmp_path / "ab.json"
    modules = [f"dyngs.fields.{name}" for name in ab.MODULES]
    before = modules_checkout(modules, tmp_path / "before")
    argv = ["--before", str(before), "--at", "2", "--steps", "2", "--threads", "1",
            "--output", str(output), "--", "hexplane-4dgs", "--data", "demo"]  # fmt: skip
    run_benchmark_main(ab, argv, monkeypatch)
    assert hexplane.sample_group is sample_group
    assert hexplane.compiled_products is compiled_products
    report = json.loads(output.read_text())
    assert report["at"] == 2 and report["pairs"] == 2
    assert report["step_ms_median"]["before"] > 0 and report["step_ms_median"]["this"] > 0
    assert (before / ".ab_step" / "before_dyngs_fields_hexplane.py").exists()

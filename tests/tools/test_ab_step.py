"""benchmarks/ab_step.py: another checkout's modules load beside this one's under their
own names, a swap puts --before's version of a name in place for the before steps only,
and the run leaves this checkout's code as it found it."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import ModuleType

import pytest
import torch

from dyngs import model
from dyngs.losses import ssim_kernels
from tests.tools.conftest import load_benchmark, modules_checkout, run_benchmark_main

ROOT = Path(__file__).resolve().parents[2]
PHOTOMETRIC = "dyngs.losses.photometric"
MODULES = ["dyngs.losses.ssim_kernels", PHOTOMETRIC, "dyngs.model"]


@pytest.fixture
def ab(monkeypatch: pytest.MonkeyPatch) -> ModuleType:
    """The script as a module; the paths and `before_*` modules it adds are undone after."""
    monkeypatch.setattr(sys, "path", list(sys.path))
    script = load_benchmark("ab_step")
    for name in MODULES:
        monkeypatch.delitem(sys.modules, script.before_name(name), raising=False)
    return script


def test_modules_load_under_their_own_names_and_import_each_other(
    ab: ModuleType, tmp_path: Path
) -> None:
    before = ab.load_before(ROOT, tmp_path, MODULES)  # this checkout, as the one to compare
    photometric = sys.modules[PHOTOMETRIC]
    assert before[PHOTOMETRIC].__name__ == "before_dyngs_losses_photometric"
    assert before[PHOTOMETRIC].ssim_map is not photometric.ssim_map
    # The lazy import of the kernels inside the loaded module is pointed at --before's.
    source = (tmp_path / "before_dyngs_losses_photometric.py").read_text()
    assert "import before_dyngs_losses_ssim_kernels as ssim_kernels" in source
    assert before["dyngs.losses.ssim_kernels"] is not ssim_kernels
    gen = torch.Generator().manual_seed(0)
    pred, target = torch.rand(2, 20, 18, 3, generator=gen)
    assert torch.equal(before[PHOTOMETRIC].ssim_map(pred, target),
                       photometric.ssim_map(pred, target))  # fmt: skip


def test_copies_are_kept_for_numbas_cache_and_fresh_kernels_are_named(
    ab: ModuleType, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    before = ab.load_before(ROOT, tmp_path, MODULES)
    copy = tmp_path / "before_dyngs_losses_ssim_kernels.py"
    written = copy.stat().st_mtime_ns
    gen = torch.Generator().manual_seed(1)
    pred, target = torch.rand(2, 20, 18, 3, generator=gen)
    before[PHOTOMETRIC].ssim_map(pred, target)  # runs the copies' kernels
    # The copies compiled in this process (into tmp_path, a cache of their own): named.
    fresh = ab.compiled_here(before.values())
    assert "before_dyngs_losses_ssim_kernels.ssim_forward" in fresh
    assert all(name.startswith("before_dyngs_losses_ssim_kernels.") for name in fresh)
    assert ab.compiled_here([before["dyngs.model"]]) == []  # no kernels at all
    # Loaded again, an unchanged copy is not rewritten: its cache stays valid.
    for name in MODULES:
        monkeypatch.delitem(sys.modules, ab.before_name(name))
    ab.load_before(ROOT, tmp_path, MODULES)
    assert copy.stat().st_mtime_ns == written


def test_a_swap_of_a_method_takes_the_raw_function_and_puts_it_back(
    ab: ModuleType, tmp_path: Path
) -> None:
    before = ab.load_before(ROOT, tmp_path, ["dyngs.model"])
    this = model.DynamicGaussians.__dict__["at"]
    swap = ab.Swap.parse("dyngs.model:DynamicGaussians.at", before)
    assert swap.this is this and swap.before is before["dyngs.model"].DynamicGaussians.at
    swap.use("before")
    try:
        assert model.DynamicGaussians.__dict__["at"] is swap.before
    finally:
        swap.use("this")
    assert model.DynamicGaussians.__dict__["at"] is this
    with pytest.raises(SystemExit, match="MODULE:NAME"):
        ab.Swap.parse("dyngs.model", before)


def test_both_ways_are_timed_and_this_checkouts_code_restored(
    ab: ModuleType, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    photometric = sys.modules[PHOTOMETRIC]
    ssim_map, at = photometric.ssim_map, model.DynamicGaussians.__dict__["at"]
    output = tmp_path / "ab.json"
    before = modules_checkout(MODULES, tmp_path / "before")
    argv = ["--before", str(before), "--swap", f"{PHOTOMETRIC}:ssim_map",
            "--swap", "dyngs.model:DynamicGaussians.at", "--with", "dyngs.losses.ssim_kernels",
            "--at", "2", "--steps", "2", "--threads", "1", "--output", str(output),
            "--", "hexplane-4dgs", "--data", "demo"]  # fmt: skip
    run_benchmark_main(ab, argv, monkeypatch)
    assert photometric.ssim_map is ssim_map and model.DynamicGaussians.__dict__["at"] is at
    report = json.loads(output.read_text())
    assert report["at"] == 2 and report["pairs"] == 2
    assert report["modules_from_before"] == [
        "dyngs.losses.ssim_kernels",
        PHOTOMETRIC,
        "dyngs.model",
    ]
    assert report["step_ms_median"]["before"] > 0 and report["step_ms_median"]["this"] > 0
    assert (before / ".ab_step" / "before_dyngs_model.py").exists()

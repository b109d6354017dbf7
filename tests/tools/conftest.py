"""One tiny trained run (three steps on the tiny built-in scene) that the eval, render,
export and view tests share (and `fading_run`, a copy whose picture changes with time);
the bench tests train their own. And `load_benchmark`, for the tests of the scripts in
benchmarks/."""

from __future__ import annotations

import importlib.util
import math
import shutil
import sys
from pathlib import Path
from types import ModuleType

import pytest
import torch

from dyngs.cli import main
from dyngs.datamanagers.procedural import demo_path
from dyngs.engine.checkpoint import load_checkpoint, save_checkpoint
from tests.engine.helpers import TINY_SCENE

TINY_FLAGS = (
    "--warmup-iters", "1", "--no-tensorboard", "--num-random-points", "500",
    "--field.resolution", "8", "8", "8", "4", "--field.multires", "1", "--field.features", "8",
)  # fmt: skip
"""dyngs-train flags that keep a run to a few milliseconds per step."""

BENCHMARKS = Path(__file__).parents[2] / "benchmarks"


def load_benchmark(name: str) -> ModuleType:
    """benchmarks/NAME.py as a module (the folder is scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # as an import would: dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def run_benchmark_main(
    module: ModuleType, argv: list[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A benchmark script's `main()` with `argv` as its command line, PyTorch's thread
    count (which the scripts set) put back afterwards."""
    monkeypatch.setattr(sys, "argv", [f"{module.__name__}.py", *argv])
    threads = torch.get_num_threads()
    try:
        module.main()
    finally:
        torch.set_num_threads(threads)


def modules_checkout(modules: list[str], folder: Path) -> Path:
    """`folder` made a stand-in for another checkout holding this one's `modules` (dotted
    names), for the A/B scripts' --before: the copies those scripts keep for numba's
    cache then land there, not in the source tree."""
    root = BENCHMARKS.parent
    for name in modules:
        source = Path(*name.split(".")).with_suffix(".py")
        (folder / source).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(root / source, folder / source)
    return folder


@pytest.fixture(scope="session")
def tiny_data() -> Path:
    return demo_path(TINY_SCENE)


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory: pytest.TempPathFactory, tiny_data: Path) -> Path:
    out = tmp_path_factory.mktemp("tools")
    main(
        ["hexplane-4dgs", "renderer:cpu-reference", "--data", str(tiny_data),
         "--output-dir", str(out), "--run-name", "run", "--max-iters", "3", *TINY_FLAGS]
    )  # fmt: skip
    return out / "run"


LIFETIME_SIGMA = 0.2
"""Time scale of the lifetimes `fading_run` gives: at t = 1 those Gaussians are drawn at
exp(−12.5) of their opacity."""


@pytest.fixture(scope="session")
def fading_run(tmp_path_factory: pytest.TempPathFactory, tiny_run: Path) -> Path:
    """The tiny run, with half of its Gaussians (left of the median x) living around t = 0
    and marked dynamic, for the viewer's tests. Three steps leave the deformation at zero
    and no Gaussian temporal, so every time would draw the same frame; edited through the
    checkpoint the viewer loads, moving the time slider must change the picture, and
    static/dynamic colouring has both colours to show."""
    run = tmp_path_factory.mktemp("viewer") / "fading"
    shutil.copytree(tiny_run, run)
    checkpoint = load_checkpoint(run / "checkpoint.pt")
    model = checkpoint["model"]
    x = model["canonical.means"][:, 0]
    fading = x < x.median()
    model["canonical.time_centers"] = torch.where(fading, 0.0, 0.5)
    model["canonical.time_log_scales"] = torch.where(
        fading, math.log(LIFETIME_SIGMA), model["canonical.time_log_scales"]
    )
    model["dynamic"] = fading.clone()
    save_checkpoint(run / "checkpoint.pt", checkpoint)
    return run

"""One tiny trained run (three steps on the tiny built-in scene) that the eval, render
and export tests share; the bench tests train their own. And `load_benchmark`, for the
tests of the scripts in benchmarks/."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

from dyngs.cli import main
from dyngs.datamanagers.procedural import demo_path
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
    spec.loader.exec_module(module)
    return module


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

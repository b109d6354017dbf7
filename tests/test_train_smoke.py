"""Every preset trains for two steps on the CPU renderer and leaves a complete run folder."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dyngs.cli import main
from dyngs.configio import load_config
from dyngs.datamanagers.procedural import demo_path
from dyngs.methods import method_presets
from tests.conftest import WEIGHTS
from tests.engine.helpers import TINY_SCENE

METRIC_KEYS = {
    "psnr",
    "ssim",
    "lpips",
    "num_gaussians",
    "train_seconds",
    "render_ms",
    "iterations",
    "renderer",
    "device",
}


def _run(tmp_path: Path, *args: str) -> tuple[Path, dict]:
    main(
        [
            *args,
            "--output-dir",
            str(tmp_path),
            "--run-name",
            "run",
            "--max-iters",
            "2",
            "--warmup-iters",
            "1",
        ]
    )
    run = tmp_path / "run"
    return run, json.loads((run / "metrics.json").read_text())


@pytest.mark.parametrize("renderer", ["cpu-reference", "cpu-tile"])
@pytest.mark.parametrize("method", sorted(method_presets()[0]))
def test_every_preset_runs_two_steps(method: str, renderer: str, tmp_path: Path) -> None:
    run, metrics = _run(
        tmp_path, method, f"renderer:{renderer}", "--data", str(demo_path(TINY_SCENE))
    )
    assert METRIC_KEYS <= set(metrics)
    assert metrics["iterations"] == 2 and metrics["renderer"] == renderer
    assert 0 < metrics["psnr"] < 100 and 0 < metrics["ssim"] <= 1 and metrics["num_gaussians"] > 0
    assert len(metrics["frames"]) == TINY_SCENE.num_test
    assert len(list((run / "test").glob("*.png"))) == TINY_SCENE.num_test
    assert load_config(run / "config.json").method == method
    assert list((run / "tensorboard").glob("events.out.tfevents.*"))
    assert (run / "checkpoint.pt").is_file()


@pytest.mark.slow
def test_default_scene_and_lpips(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The README's first command, shortened; LPIPS is reported when its weights exist."""
    if not WEIGHTS.is_dir():
        pytest.skip(f"LPIPS weights {WEIGHTS} are not present")
    monkeypatch.setenv("TORCH_HOME", str(WEIGHTS))
    _, metrics = _run(tmp_path, "hexplane-4dgs", "--data", "demo")
    assert metrics["lpips"] is not None and 0 <= metrics["lpips"] <= 1


def test_resume_continues_a_finished_run(tmp_path: Path) -> None:
    run, first = _run(tmp_path, "hexplane-4dgs", "--data", str(demo_path(TINY_SCENE)))
    main(["--resume", str(run)])
    again = json.loads((run / "metrics.json").read_text())
    assert again["iterations"] == first["iterations"]
    assert again["psnr"] == pytest.approx(first["psnr"])

"""dyngs-eval: the JSON has every key with sane values, LPIPS is null (not a crash) where
it cannot be computed, and a bad run folder is a one-line error."""

from __future__ import annotations

import itertools
import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any, cast

import pytest
import torch

from dyngs.engine import evaluate as evaluate_module
from dyngs.metrics import LPIPS
from dyngs.renderers import Renderer
from dyngs.runs import load_run
from dyngs.tools.eval import main
from tests.conftest import WEIGHTS
from tests.engine.helpers import TINY_SCENE

EVAL_KEYS = {
    "split", "num_frames", "psnr", "ssim", "lpips", "render_ms", "render_ms_median",
    "render_ms_p95", "warmup_renders", "peak_memory_mb", "peak_memory_source", "frames",
    "num_gaussians", "train_seconds", "iterations", "renderer", "device", "sh_degree",
    "deformation_ms", "dynamic_fraction", "model_bytes",
}  # fmt: skip


def _strict_json(path: Path) -> dict[str, Any]:
    def refuse(token: str) -> None:
        raise AssertionError(f"{path} holds {token}")

    return json.loads(path.read_text(), parse_constant=refuse)


def test_eval_json_and_images(tiny_run: Path) -> None:
    main(["--load-dir", str(tiny_run), "--warmup", "1"])
    metrics = _strict_json(tiny_run / "eval_test.json")
    assert EVAL_KEYS <= set(metrics)
    assert metrics["split"] == "test" and metrics["num_frames"] == TINY_SCENE.num_test
    assert 0 < metrics["psnr"] < 100 and 0 < metrics["ssim"] <= 1
    assert metrics["lpips"] is None or 0 <= metrics["lpips"] <= 1
    assert 0 < metrics["render_ms_median"] <= metrics["render_ms_p95"]
    assert metrics["peak_memory_mb"] > 0 and metrics["iterations"] == 3
    assert len(metrics["frames"]) == TINY_SCENE.num_test
    for frame in metrics["frames"]:
        assert {"index", "time", "psnr", "ssim", "lpips", "render_ms"} <= set(frame)
        assert 0 <= frame["time"] <= 1 and frame["render_ms"] > 0
    assert len(list((tiny_run / "eval_test").glob("*.png"))) == TINY_SCENE.num_test


def test_eval_other_split_and_output(tiny_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "val.json"
    main(["--load-dir", str(tiny_run), "--split", "val", "--no-save-images", "--output", str(out)])
    metrics = _strict_json(out)
    assert metrics["split"] == "val" and metrics["num_frames"] == TINY_SCENE.num_val


def test_lpips_with_weights(
    tiny_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    if not WEIGHTS.is_dir():
        pytest.skip(f"LPIPS weights {WEIGHTS} are not present")
    monkeypatch.setenv("TORCH_HOME", str(WEIGHTS))
    out = tmp_path / "eval.json"
    main(["--load-dir", str(tiny_run), "--no-save-images", "--warmup", "0", "--output", str(out)])
    metrics = _strict_json(out)
    assert metrics["lpips"] is not None and 0 <= metrics["lpips"] <= 1


def test_perfect_render_and_small_images_stay_valid_json(
    tiny_run: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A render identical to its ground truth (PSNR = inf) and images below LPIPS's
    minimum size give null, never Infinity or a crash."""
    run = load_run(tiny_run)
    data = run.data()
    # Every view is drawn twice in order: once timed, once scored.
    images = itertools.cycle([v.image for v in data.views("test")])

    def perfect(gaussians: object, camera: object, background: object) -> SimpleNamespace:
        return SimpleNamespace(rgb=next(images))

    def never_called(*args: object) -> torch.Tensor:
        raise AssertionError("LPIPS ran on images below its minimum size")

    monkeypatch.setattr(evaluate_module, "load_lpips", lambda device: never_called)
    monkeypatch.setattr(LPIPS, "MIN_SIZE", 10_000)
    with pytest.warns(UserWarning, match="LPIPS needs images"):
        metrics = evaluate_module.evaluate(
            run.model,
            cast(Renderer, perfect),
            data,
            "test",
            None,
            run.device,
            warmup=0,
        )
    assert metrics["psnr"] is None and metrics["lpips"] is None
    assert all(f["psnr"] is None and f["ssim"] == pytest.approx(1.0) for f in metrics["frames"])
    json.dumps(metrics, allow_nan=False)


@pytest.mark.parametrize("problem", ["missing", "no-checkpoint", "broken-config"])
def test_bad_run_folder_is_one_line(
    problem: str, tiny_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "run"
    if problem == "no-checkpoint":
        run.mkdir()
        (run / "config.json").write_text((tiny_run / "config.json").read_text())
    elif problem == "broken-config":
        run.mkdir()
        (run / "config.json").write_text('{"no": "class"}')
    with pytest.raises(SystemExit) as exit_info:
        main(["--load-dir", str(run)])
    assert exit_info.value.code == 2
    err = capsys.readouterr().out.strip()
    assert err.startswith("error:") and "\n" not in err and str(run) in err

"""A finished run folder stands alone: render and export work when its dataset has been
moved away, the model it loads draws exactly what training drew, and evaluation, which
must read the images, says where they went."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from dyngs.cli import main as train
from dyngs.datamanagers.scene_info import SCENE_FILE, SceneInfo
from dyngs.model import DynamicGaussians
from dyngs.runs import load_run
from dyngs.tools.eval import main as evaluate
from dyngs.tools.export import main as export
from dyngs.tools.render import main as render
from tests.tools.conftest import TINY_FLAGS


@pytest.fixture(scope="module")
def orphan(tmp_path_factory: pytest.TempPathFactory, tiny_data: Path) -> tuple[Path, Path]:
    """A run trained on a copy of the tiny scene, and where that copy was moved to."""
    root = tmp_path_factory.mktemp("orphan")
    data = root / "scene"
    shutil.copytree(tiny_data, data)
    train(
        ["hexplane-4dgs", "renderer:cpu-reference", "--data", str(data),
         "--output-dir", str(root), "--run-name", "run", "--max-iters", "4", *TINY_FLAGS]
    )  # fmt: skip
    moved = root / "scene-moved"
    data.rename(moved)
    return root / "run", moved


def test_export_without_the_dataset(orphan: tuple[Path, Path]) -> None:
    run, _ = orphan
    export(["--load-dir", str(run), "--all-times"])
    files = sorted((run / "export" / "all_times").glob("*.ply"))
    times = SceneInfo.read(run / SCENE_FILE).train.times
    assert len(files) == len(set(times.tolist())) > 1


@pytest.mark.parametrize("trajectory", ["spiral", "test", "fixed"])
def test_render_without_the_dataset(orphan: tuple[Path, Path], trajectory: str) -> None:
    run, _ = orphan
    out = run / f"{trajectory}.mp4"
    render(["--load-dir", str(run), "--trajectory", trajectory, "--frames", "3",
            "--output", str(out)])  # fmt: skip
    assert out.stat().st_size > 0


def test_eval_says_where_the_images_went_and_takes_their_new_place(
    orphan: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    run, moved = orphan
    with pytest.raises(SystemExit) as exit_info:
        evaluate(["--load-dir", str(run), "--no-save-images"])
    assert exit_info.value.code == 2
    text = capsys.readouterr().out.strip()
    assert "does not exist" in text and "--data NEW_PATH" in text and len(text.splitlines()) == 1
    evaluate(["--load-dir", str(run), "--no-save-images", "--data", str(moved)])
    metrics = json.loads((run / "eval_test.json").read_text())
    trained = json.loads((run / "metrics.json").read_text())
    assert metrics["psnr"] == pytest.approx(trained["psnr"], abs=1e-9)


def test_the_state_dict_holds_what_the_model_draws_with(orphan: tuple[Path, Path]) -> None:
    """The loaded model's SH degree, deformation flag, dynamic flags and box come from its
    own state, and a model rebuilt from that state alone draws the same Gaussians."""
    run, _ = orphan
    loaded = load_run(run)
    state = loaded.model.state_dict()
    extra = state["_extra_state"]
    assert extra["deforming"] is True  # four steps past a one-step warm-up
    assert extra["active_sh_degree"] == loaded.model.active_sh_degree
    assert extra["box"] == [list(loaded.scene.scene_box.lower), list(loaded.scene.scene_box.upper)]
    assert state["dynamic"].dtype == torch.bool
    config = loaded.config
    again = DynamicGaussians.load(config.gaussians, config.field, config.head, state)
    for t in (0.0, 0.6):
        a, b = loaded.model.at(t), again.at(t)
        for name in ("means", "quats", "scales", "opacities", "colors"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name


def test_a_state_from_another_box_is_refused(orphan: tuple[Path, Path]) -> None:
    run, _ = orphan
    loaded = load_run(run)
    state = loaded.model.state_dict()
    state["_extra_state"] = dict(state["_extra_state"], box=[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    with pytest.raises(ValueError, match="scene box"):
        loaded.model.load_state_dict(state)

"""benchmarks/psnr_by_view.py: frames are grouped by camera position, and each group's
elevation, error share and neighbouring training views are what the cameras say."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from dyngs.datamanagers.scene_info import SCENE_FILE, SceneInfo, Views
from dyngs.types import Camera, SceneBox
from tests.tools.conftest import load_benchmark

psnr_by_view = load_benchmark("psnr_by_view")

TOP, SIDE, LOW = (0.0, 0.0, 5.0), (5.0, 0.0, 0.0), (5.0, 0.0, 0.5)


def _camera(position: tuple[float, float, float], turn: float = 0.0) -> Camera:
    """A camera at `position` (its orientation, a turn about z, does not matter here)."""
    c, s = math.cos(turn), math.sin(turn)
    rotation = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    w2c = torch.eye(4)
    w2c[:3, :3] = rotation
    w2c[:3, 3] = -rotation @ torch.tensor(position)  # so that −Rᵀt is the position
    return Camera(fx=50.0, fy=50.0, cx=16.0, cy=16.0, world_to_camera=w2c, width=32, height=32)


def _run(tmp_path: Path) -> Path:
    train = [TOP, SIDE, SIDE, SIDE, LOW, LOW]
    test = [SIDE, TOP, SIDE, TOP]
    scene = SceneInfo(
        name="rig",
        scene_box=SceneBox((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)),
        background=torch.ones(3),
        train=Views([_camera(p, 0.1 * i) for i, p in enumerate(train)], torch.linspace(0, 1, 6)),
        val=Views([], torch.zeros(0)),
        test=Views([_camera(p) for p in test], torch.linspace(0.1, 0.9, 4)),
    )
    run = tmp_path / "run"
    run.mkdir()
    scene.write(run / SCENE_FILE)
    frames = [{"index": i, "psnr": p} for i, p in enumerate([30.0, 20.0, 32.0, 22.0])]
    (run / "metrics.json").write_text(json.dumps({"split": "test", "frames": frames}))
    return run


def test_groups_by_camera(tmp_path: Path) -> None:
    run = _run(tmp_path)
    output = tmp_path / "views.json"
    psnr_by_view.main([str(run), "--within", "10", "--output", str(output)])
    top, side = json.loads(output.read_text())["runs"][0]["views"]  # worst first
    assert top["position"] == pytest.approx(TOP, abs=1e-4) and side["position"] == pytest.approx(
        SIDE, abs=1e-4
    )
    assert top["elevation"] == pytest.approx(90.0) and side["elevation"] == pytest.approx(0.0)
    assert (top["frames"], top["psnr"], side["psnr"]) == (2, 21.0, 31.0)
    errors = {name: 10 ** (-p / 10) for name, p in {"a": 30, "b": 20, "c": 32, "d": 22}.items()}
    assert top["error_share"] == pytest.approx((errors["b"] + errors["d"]) / sum(errors.values()))
    assert top["error_share"] + side["error_share"] == pytest.approx(1.0)
    assert (top["train_same_camera"], side["train_same_camera"]) == (1, 3)
    # LOW lies 5.7° above the side direction from the box centre and 84° from the top.
    assert (top["train_within"], side["train_within"]) == (1, 5)


def test_runs_without_scores_are_skipped(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    run = _run(tmp_path)
    psnr_by_view.main([str(run), "--split", "train"])  # no eval_train.json
    assert "no train scores" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        psnr_by_view.main([str(run), "--within", "200"])

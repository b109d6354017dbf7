"""A short training run on each capture format lowers the loss, and `dyngs-train
hexplane-4dgs --data FOLDER` runs on each with no other flag."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest

from dyngs.cli import main
from dyngs.datamanagers.datamanager import DataConfig
from dyngs.engine.trainer import Trainer
from dyngs.engine.writer import NullWriter
from tests.datamanagers.formats import Truth, write_dynerf, write_nerfies, write_panoptic
from tests.engine.helpers import tiny_config

STEPS = 20
WINDOW = 5

# Small images keep a CPU step near 0.1 s; the CLI run below uses the preset's defaults
# (20k random points without a cloud), so every capture brings its own point cloud.
WRITERS: dict[str, Callable[[Path], Truth]] = {
    "panoptic": lambda folder: write_panoptic(folder, timesteps=3, size=(24, 18)),
    "dynerf": lambda folder: write_dynerf(folder, size=(24, 24), point_cloud=True),
    "nerfies": lambda folder: write_nerfies(folder, size=(24, 18), points=True),
}


@pytest.fixture(scope="module", params=sorted(WRITERS))
def capture(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp(request.param)
    WRITERS[request.param](folder)
    return folder


def test_short_training_lowers_the_loss(capture: Path, tmp_path: Path) -> None:
    config = tiny_config(
        data=str(capture), max_iters=STEPS, dataset=DataConfig(num_random_points=300)
    )
    trainer = Trainer(config, tmp_path, NullWriter())
    losses = [float(trainer.train_step(step).loss) for step in range(STEPS)]
    first, last = sum(losses[:WINDOW]) / WINDOW, sum(losses[-WINDOW:]) / WINDOW
    assert last < 0.95 * first, losses


def test_dyngs_train_runs_with_only_the_data_flag(capture: Path, tmp_path: Path) -> None:
    main(
        ["hexplane-4dgs", "--data", str(capture), "--max-iters", "2", "--output-dir", str(tmp_path)]
    )
    (run,) = tmp_path.iterdir()
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["iterations"] == 2 and 0 < metrics["psnr"] < 100

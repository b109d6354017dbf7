"""benchmarks/track_by_time.py: the fit by time agrees with the evaluation, rows follow the
training, and the command line writes its table."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

from dyngs.engine import schedules
from dyngs.engine.evaluate import evaluate
from tests.engine.helpers import tiny_trainer
from tests.tools.conftest import TINY_FLAGS, load_benchmark

track_by_time = load_benchmark("track_by_time")


def test_one_span_is_the_mean_psnr_of_the_training_views(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path, warmup_iters=1)
    for step in range(3):
        trainer.train_step(step)
    trainer.step = 3
    (whole,) = track_by_time.fit_by_time(trainer, 1)
    reference = evaluate(
        trainer.model, trainer.renderer, trainer.data, "train", image_dir=None,
        device=torch.device("cpu"),
    )  # fmt: skip
    assert whole == pytest.approx(reference["psnr"], rel=1e-9)


def test_rows_follow_the_training_from_the_end_of_the_warm_up(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path, max_iters=9, warmup_iters=3, time_ramp=0.5)
    rows = track_by_time.track(trainer, every=2, bins=3)
    assert [row["step"] for row in rows] == [4, 6, 8]
    windows = [schedules.time_window(trainer.config, s) for s in (4, 6, 8)]
    assert [row["window"] for row in rows] == windows
    assert all(len(row["psnr_by_time"]) == 3 for row in rows)
    assert all(p is not None and 5 < p < 60 for row in rows for p in row["psnr_by_time"])
    assert trainer.step == 9


def test_the_command_line_writes_its_table(
    tmp_path: Path, tiny_data: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    output = tmp_path / "track.json"
    train_args = ["hexplane-4dgs", "--data", str(tiny_data), "--max-iters", "4", *TINY_FLAGS]
    argv = ["track_by_time.py", "--every", "2", "--bins", "2", "--output", str(output), "--"]
    monkeypatch.setattr(sys, "argv", argv + train_args)
    track_by_time.main()
    table = json.loads(output.read_text())
    assert table["train_args"] == train_args and table["bins"] == 2
    assert [row["step"] for row in table["rows"]] == [2, 4]

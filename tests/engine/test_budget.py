"""Training sized to the scene and to the user's time: the data-sized step count, and
`--time-budget`'s re-planning, checked with given clocks (never the machine's)."""

from __future__ import annotations

from pathlib import Path

import pytest

from dyngs.config import TrainConfig
from dyngs.engine import budget as budget_module
from dyngs.engine.budget import TimeBudget
from dyngs.engine.capacity import STEPS_LIMITS, training_steps
from dyngs.errors import ConfigError
from tests.engine.helpers import tiny_trainer


def test_a_steady_rate_plans_the_steps_that_fit() -> None:
    budget = TimeBudget(seconds=100.0, ceiling=10_000)
    planned = 3000
    for step in range(0, 1001, 100):  # 20 steps per second
        changed = budget.plan(step, step / 20.0, planned)
        planned = changed if changed is not None else planned
    assert planned == pytest.approx(2000, rel=budget_module.REPLAN_TOLERANCE)


def test_a_slowing_run_is_shortened_and_never_past_the_ceiling() -> None:
    fast = TimeBudget(seconds=1000.0, ceiling=5000)
    assert fast.plan(100, 0.1, 3000) is None  # one mark: no rate yet
    assert fast.plan(200, 0.2, 3000) == 5000  # a million steps would fit: the ceiling
    slow = TimeBudget(seconds=60.0, ceiling=5000)
    slow.plan(1000, 50.0, 3000)
    # 20 steps per second with 5 s left: 100 more steps.
    assert slow.plan(1100, 55.0, 3000) == 1200
    over = TimeBudget(seconds=10.0, ceiling=5000)
    over.plan(100, 5.0, 3000)
    assert over.plan(200, 20.0, 3000) == 201  # past the budget: stop at once


def test_small_moves_and_the_last_tenth_keep_the_plan() -> None:
    budget = TimeBudget(seconds=150.0, ceiling=10_000)
    budget.plan(0, 0.0, 3000)
    assert budget.plan(1000, 50.0, 3000) is None  # 3000 steps at 20/s: 150 s, as planned
    settled = TimeBudget(seconds=1.0, ceiling=10_000)
    settled.plan(2500, 10.0, 3000)
    assert settled.plan(2800, 20.0, 3000) is None  # in the last tenth


def test_the_trainer_replans_saves_and_resumes_its_plan(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path, max_iters=400, time_budget=1.0)  # 60 s
    assert trainer.budget is not None and trainer.config.steps == 400
    trainer.step, trainer.counters.train_seconds = 0, 0.0
    trainer.replan()
    trainer.step, trainer.counters.train_seconds = 100, 50.0  # 2 steps per second
    trainer.replan()
    assert trainer.config.steps == 120  # 10 s left: 20 more steps
    assert trainer.lifecycle.config is trainer.config
    trainer.save()
    again = tiny_trainer(tmp_path / "again", max_iters=400, time_budget=1.0)
    again.load(trainer.checkpoint_path())
    assert again.config.steps == 120 and again.budget is not None
    assert again.budget.marks == trainer.budget.marks


def test_without_a_budget_the_plan_is_the_config(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path, max_iters=30)
    trainer.step, trainer.counters.train_seconds = 20, 1e6
    trainer.replan()
    assert trainer.config.steps == 30


def test_steps_are_sized_from_the_timestamps(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path, max_iters=None)
    assert trainer.sized_steps and trainer.config.steps == training_steps(trainer.scene)
    assert STEPS_LIMITS[0] <= trainer.config.steps <= STEPS_LIMITS[1]
    assert any("sized from the data" in note for note in trainer.notes())
    explicit = tiny_trainer(tmp_path / "explicit", max_iters=77)
    assert not explicit.sized_steps and explicit.config.steps == 77


def test_bad_budgets_are_refused() -> None:
    for minutes in (0.0, -1.0, float("nan")):
        with pytest.raises(ConfigError, match="--time-budget"):
            TrainConfig(time_budget=minutes)
    with pytest.raises(ConfigError, match="not sized"):
        _ = TrainConfig().steps

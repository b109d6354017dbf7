"""Training sized to the scene and to the user's time: the data-sized step count, and
`--time-budget`'s re-planning, checked with given clocks (never the machine's)."""

from __future__ import annotations

import dataclasses
import io
from pathlib import Path

import pytest
from rich.console import Console

from dyngs.config import TrainConfig
from dyngs.engine import budget as budget_module
from dyngs.engine import schedules
from dyngs.engine.budget import TimeBudget
from dyngs.engine.capacity import STEPS_LIMITS, training_steps
from dyngs.engine.optim import OptimConfig
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
    # 60 s; the deformation's rates are those of 200 steps, so 400 planned take half.
    optim = OptimConfig(deformation_steps=200)
    trainer = tiny_trainer(tmp_path, max_iters=400, time_budget=1.0, optim=optim)
    trainer.console = Console(file=io.StringIO(), width=200)
    assert trainer.budget is not None and trainer.config.steps == 400
    assert any(
        "at 0.50× --optim.grid" in note and "each re-plan of the budget sizes it again" in note
        for note in trainer.notes()
    )
    trainer.step, trainer.counters.train_seconds = 1, 0.0  # in the warm-up: no re-plan
    trainer.replan()
    assert trainer.budget.marks == []
    trainer.step, trainer.counters.train_seconds = 10, 5.0
    trainer.replan()
    trainer.step, trainer.counters.train_seconds = 110, 55.0  # 2 steps per second
    trainer.replan()
    assert trainer.config.steps == 120  # 5 s left: 10 more steps
    said = trainer.console.file.getvalue()  # type: ignore[attr-defined]
    assert "120 steps fit the 5 s left (the deformation at 1.00× its rates)" in said
    assert trainer.config.pace == (110, 110.0, 400)  # the 400-step schedule, sped up
    assert trainer.lifecycle.config is trainer.config
    trainer.save()
    again = tiny_trainer(tmp_path / "again", max_iters=400, time_budget=1.0, optim=optim)
    again.load(trainer.checkpoint_path())
    assert again.config.steps == 120 and again.budget is not None
    assert again.config.pace == trainer.config.pace
    assert again.budget.marks == trainer.budget.marks


def test_a_replan_changes_the_pace_and_never_moves_the_schedule_back() -> None:
    config = TrainConfig(max_iters=1000, warmup_iters=200, time_ramp=0.5)
    assert all(schedules.position(config, s) == s for s in (0, 200, 555, 1000))
    # The budget finds at step 400 that 2000 steps fit, then at 1500 that only 1700 do.
    longer = schedules.repaced(config, 400, 2000)
    shorter = schedules.repaced(longer, 1500, 1700)
    for before, after, step in ((config, longer, 400), (longer, shorter, 1500)):
        assert schedules.position(after, step) == pytest.approx(schedules.position(before, step))
        assert schedules.time_window(after, step) == pytest.approx(
            schedules.time_window(before, step)
        )
        assert schedules.learning_progress(after, step)[0] == pytest.approx(
            schedules.learning_progress(before, step)[0]
        )
    # Only recomputing the fractions from the new count would have narrowed the window.
    naive = dataclasses.replace(config, max_iters=2000)
    assert schedules.time_window(naive, 400) < schedules.time_window(config, 400)

    def along(cfg: TrainConfig, steps: range) -> list[float]:
        return [schedules.time_window(cfg, s) for s in steps]

    windows = along(longer, range(400, 1501)) + along(shorter, range(1500, 1701))
    assert windows == sorted(windows) and windows[-1] == 1.0
    assert schedules.learning_progress(shorter, 1700)[0] == pytest.approx(1.0)
    assert schedules.length(shorter) == 1000
    # Densification ends where the 1000-step schedule puts it, half way along it.
    refining = [s for s in range(400, 1501) if schedules.is_refine_step(longer, s)]
    last, every = refining[-1], config.densify.refine_every
    assert schedules.position(longer, last) <= 500 < schedules.position(longer, last + every)


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

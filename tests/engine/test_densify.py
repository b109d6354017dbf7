from __future__ import annotations

import dataclasses
import io
import math
from pathlib import Path

import pytest
import torch
from rich.console import Console

from dyngs.engine import schedules
from dyngs.engine.densify import DensifyConfig, apply_topology, plan_refinement
from dyngs.errors import ConfigError
from dyngs.model import ETERNAL, GAUSSIAN_PARAMS
from tests.engine.helpers import tiny_config, tiny_trainer


def _train_a_little(tmp_path: Path):  # type: ignore[no-untyped-def]
    trainer = tiny_trainer(tmp_path)
    for step in range(3):
        trainer.train_step(step)
    return trainer


def test_clone_split_prune_keep_every_per_gaussian_tensor_in_step(tmp_path: Path) -> None:
    trainer = _train_a_little(tmp_path)
    model, state = trainer.model, trainer.lifecycle.state
    n = len(model.canonical)
    # Fabricate gradient statistics: the first third clones or splits, one is transparent.
    state.grad_sum[: n // 3] = 1.0
    state.count[:] = 1.0
    with torch.no_grad():
        model.canonical.opacity_logits[-1] = -20.0
        model.canonical.log_scales[0] = 5.0  # huge: must be split, not cloned
    config = DensifyConfig(reset_opacity_every=0, prune_importance=0.0)
    plan = plan_refinement(config, model, state, step=100, extent=trainer.extent)
    assert plan is not None
    change, values = plan
    apply_topology(model, trainer.optimizer, change, values)

    m = len(model.canonical)
    assert m == len(change.source) and m > n
    for name in GAUSSIAN_PARAMS:
        param = getattr(model.canonical, name)
        assert param.shape[0] == m
        for moment in trainer.optimizer.state[param].values():
            if moment.ndim > 0:
                assert moment.shape[0] == m, name
    assert model.dynamic.shape == (m,)
    assert not bool((change.source == n - 1).any())  # the transparent one is gone
    assert int((change.source == 0).sum()) == config.split_children  # the huge one was split
    children = model.canonical.log_scales[change.source == 0]
    assert torch.allclose(
        children, torch.full_like(children, 5.0 - torch.log(torch.tensor(1.6)).item())
    )
    # Training goes on with the new set.
    trainer.lifecycle.state = type(state).zeros(m, trainer.device)
    trainer.train_step(4)


def test_budget_caps_growth(tmp_path: Path) -> None:
    trainer = _train_a_little(tmp_path)
    model, state = trainer.model, trainer.lifecycle.state
    n = len(model.canonical)
    state.grad_sum[:] = torch.rand(n, generator=torch.Generator().manual_seed(0)) * 1e-2
    state.count[:] = 1.0
    config = DensifyConfig(
        max_gaussians=n + 10, refine_start=0, refine_stop=0.5, prune_importance=0.0
    )
    budget = schedules.budget_at(tiny_config(max_iters=1000, densify=config), 1000)
    plan = plan_refinement(config, model, state, step=1000, extent=trainer.extent, budget=budget)
    assert plan is not None
    assert n < len(plan[0].source) <= n + 10


def test_budget_grows_on_a_schedule() -> None:
    config = tiny_config(
        max_iters=1100,
        densify=DensifyConfig(max_gaussians=1000, refine_start=100, refine_stop=0.5),
    )
    caps = [schedules.budget_at(config, step) for step in (0, 100, 325, 550, 1000)]
    assert caps == [250, 250, 625, 1000, 1000]
    unbounded = tiny_config(max_iters=100, densify=DensifyConfig(max_gaussians=None))
    assert schedules.budget_at(unbounded, 10) > 10**12


def test_refinements_pause_after_each_reset() -> None:
    def refining(pause: int) -> list[int]:
        densify = DensifyConfig(refine_start=100, refine_every=100, refine_stop=0.5,
                                reset_opacity_every=1000, pause_after_reset=pause)  # fmt: skip
        config = tiny_config(max_iters=5000, densify=densify)
        return [s for s in range(5001) if schedules.is_refine_step(config, s)]

    on_schedule = list(range(100, 2501, 100))
    assert refining(0) == on_schedule
    # The refinement at a reset step comes before its reset and stays; the two after each
    # reset within refine_stop (1 000 and 2 000) are skipped, and none after 2 500.
    paused = [s for s in on_schedule if s not in (1100, 1200, 2100, 2200)]
    assert refining(200) == paused
    assert refining(250) == paused


def test_importance_views_must_not_be_negative() -> None:
    with pytest.raises(ConfigError, match="importance-views must be ≥ 0"):
        DensifyConfig(importance_views=-1)
    with pytest.raises(ConfigError, match="pause-after-reset must be ≥ 0"):
        DensifyConfig(pause_after_reset=-1)
    for life in (-0.1, float("nan")):
        with pytest.raises(ConfigError, match="grow-min-life must be ≥ 0"):
            DensifyConfig(grow_min_life=life)


def test_gaussians_that_live_a_few_frames_do_not_grow(tmp_path: Path) -> None:
    """With every Gaussian asking to grow, one whose temporal σ is under `grow_min_life` is
    neither cloned nor split, one just above it and an eternal one are; at 0 (and before
    the data sized it, None) all three grow."""
    trainer = _train_a_little(tmp_path)
    model, state = trainer.model, trainer.lifecycle.state
    state.grad_sum[:] = 1.0
    state.count[:] = 1.0
    with torch.no_grad():
        model.canonical.time_log_scales[0] = math.log(0.02)  # two to three frames of 126
        model.canonical.time_log_scales[1] = math.log(0.06)
        model.canonical.time_log_scales[2] = ETERNAL
        model.canonical.log_scales[:3] = 5.0  # large: split, not cloned
    grown = {}
    for life in (0.05, 0.0, None):
        config = DensifyConfig(reset_opacity_every=0, prune_importance=0.0, grow_min_life=life)
        plan = plan_refinement(config, model, state, step=100, extent=trainer.extent)
        assert plan is not None
        grown[life] = [int((plan[0].source == i).sum()) for i in range(3)]
    children = DensifyConfig().split_children
    assert grown[0.05] == [1, children, children]
    assert grown[0.0] == grown[None] == [children] * 3


def test_gaussians_whose_lifetime_left_the_sequence_are_pruned(tmp_path: Path) -> None:
    """Opaque Gaussians are pruned when their presence at every time in [0, 1] leaves them
    under `prune_opacity`: τ far past the end, or before the start; kept when τ is just
    past an end (still present there) and when eternal, whatever their τ."""
    trainer = _train_a_little(tmp_path)
    model, state = trainer.model, trainer.lifecycle.state
    lives = [(1.5, 0.05), (-0.4, 0.1), (1.05, 0.05), (0.5, 0.01), (5.0, math.inf)]
    with torch.no_grad():
        c = model.canonical
        c.opacity_logits[: len(lives)] = 5.0
        for i, (tau, sigma) in enumerate(lives):
            c.time_centers[i] = tau
            c.time_log_scales[i] = math.log(sigma) if math.isfinite(sigma) else ETERNAL
    peak = model.canonical.peak_presence()[: len(lives)]
    expected = [math.exp(-0.5 * ((min(max(tau, 0), 1) - tau) / s) ** 2) for tau, s in lives]
    assert peak.tolist() == pytest.approx(expected, rel=1e-5)
    config = DensifyConfig(reset_opacity_every=0, prune_importance=0.0)
    plan = plan_refinement(config, model, state, step=100, extent=trainer.extent)
    assert plan is not None
    kept = [bool((plan[0].source == i).any()) for i in range(len(lives))]
    assert kept == [False, False, True, True, True]


def test_absgrad_accumulates_the_absolute_gradient_and_meets_its_own_threshold(
    tmp_path: Path,
) -> None:
    # The same two steps with either statistic: the parameters stay identical (statistics
    # never touch them before a refinement), and the absolute gradient is at least the
    # gradient for every Gaussian, and larger in total (terms of both signs cancel).
    plain = tiny_trainer(tmp_path / "plain", densify=DensifyConfig(absgrad=False))
    absolute = tiny_trainer(tmp_path / "abs", densify=DensifyConfig(absgrad=True))
    for trainer in (plain, absolute):
        for step in range(2):
            trainer.train_step(step)
    grad, absgrad = plain.lifecycle.state.grad_sum, absolute.lifecycle.state.grad_sum
    assert torch.equal(plain.model.canonical.means, absolute.model.canonical.means)
    assert bool((absgrad >= grad * (1 - 1e-6)).all()) and float(absgrad.sum()) > float(grad.sum())

    # Refinement compares the mean against the statistic's own threshold.
    model, state = plain.model, plain.lifecycle.state
    state.grad_sum[:] = 5e-4  # above the gradient's 2e-4, below the absolute gradient's 8e-4
    state.count[:] = 1.0
    for use_abs, grows in ((False, True), (True, False)):
        config = DensifyConfig(absgrad=use_abs, reset_opacity_every=0, prune_importance=0.0)
        plan = plan_refinement(config, model, state, step=100, extent=plain.extent)
        grew = plan is not None and len(plan[0].source) > len(model.canonical)
        assert grew == grows, use_abs


def test_a_renderer_without_the_absolute_gradient_falls_back_to_the_gradient(
    tmp_path: Path,
) -> None:
    trainer = tiny_trainer(tmp_path)
    assert trainer.config.densify.absgrad  # the default
    inner = trainer.renderer

    def without_absgrad(*args, **kwargs):  # type: ignore[no-untyped-def]
        return dataclasses.replace(inner(*args, **kwargs), means2d_absgrad=None)

    trainer.renderer = without_absgrad  # type: ignore[assignment]
    trainer.lifecycle.console = Console(file=io.StringIO(), width=200)
    for step in range(2):
        trainer.train_step(step)
    assert not trainer.config.densify.absgrad and not trainer.lifecycle.config.densify.absgrad
    said = trainer.lifecycle.console.file.getvalue()  # type: ignore[attr-defined]
    assert said.count("cannot measure the absolute gradient") == 1
    assert float(trainer.lifecycle.state.grad_sum.sum()) > 0


def test_large_on_screen_prunes_only_when_asked(tmp_path: Path) -> None:
    """After the first reset a Gaussian wide on screen is kept by default (3DGS's code never
    applied its 20 px rule: the radii were zeroed before the check), and pruned with
    `--densify.prune-screen-size`; one large in the world is pruned either way."""
    trainer = _train_a_little(tmp_path)
    model, state = trainer.model, trainer.lifecycle.state
    n = len(model.canonical)
    state.count[:] = 1.0
    state.max_radius[:] = 5.0
    state.max_radius[1] = 500.0  # wide on screen, small in the world
    with torch.no_grad():
        model.canonical.log_scales[2] = 10.0  # large in the world
    quiet = DensifyConfig(reset_opacity_every=100, prune_importance=0.0, grad_threshold=1e9,
                          absgrad=False)  # fmt: skip
    for screen, pruned in ((0.0, {2}), (20.0, {1, 2})):
        config = dataclasses.replace(quiet, prune_screen_size=screen)
        plan = plan_refinement(config, model, state, step=200, extent=trainer.extent)
        assert plan is not None, screen
        kept = set(plan[0].source.tolist())
        assert set(range(n)) - kept == pruned, screen

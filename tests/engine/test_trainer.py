from __future__ import annotations

import dataclasses
import itertools
import math
from pathlib import Path

import pytest
import torch

from dyngs.datamanagers.datamanager import DataConfig
from dyngs.engine import schedules
from dyngs.engine.densify import DensifyConfig
from dyngs.engine.trainer import Trainer, time_noise
from dyngs.engine.writer import NullWriter
from dyngs.metrics import psnr
from dyngs.model import GaussianConfig
from dyngs.renderers.base import ContributionRenderer
from dyngs.types import Gaussians
from tests.conftest import shared_scene
from tests.engine.helpers import (
    assert_same_state,
    field_calls,
    gradients_reaching,
    output_layer,
    tiny_config,
    tiny_trainer,
)


def test_gradients_reach_every_parameter_group(tmp_path: Path) -> None:
    # SH degree raised every step, so the higher coefficients are in play from step 1.
    trainer = tiny_trainer(tmp_path, warmup_iters=0, gaussians=GaussianConfig(sh_degree_interval=1))
    # Every other Gaussian with temporal opacity (the rest eternal), so that its τ and σ
    # are in play.
    with torch.no_grad():
        trainer.model.canonical.time_log_scales[::2] = math.log(0.3)
    named, reached = gradients_reaching(trainer.model)
    # The head's last layers start at zero, so its inner layers and the field first get a
    # gradient on the second step.
    for step in range(3):
        trainer.train_step(step)
    assert reached == named, named - reached
    assert any(n.startswith("field.grids") for n in reached)
    assert any(n.startswith("head.") for n in reached)


def test_step_zero_renders_the_canonical_scene(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path)
    deformed = trainer.model.at(0.37, sh_degree=0, deform=True)
    canonical = trainer.model.at(0.37, sh_degree=0, deform=False)
    for name in ("means", "quats", "scales", "opacities", "colors"):
        assert torch.equal(getattr(deformed, name), getattr(canonical, name)), name


def test_static_gaussians_never_query_the_field(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path)
    model = trainer.model
    with torch.no_grad():
        layer = output_layer(model.head, "means")
        assert layer is not None
        layer.bias.fill_(0.1)  # every dynamic Gaussian moves
    model.dynamic[::2] = False
    seen = field_calls(model.field)
    moved = model.at(0.5, sh_degree=0, deform=True).means
    assert seen == [int(model.dynamic.sum())]
    still = model.canonical.means
    assert torch.equal(moved[~model.dynamic], still[~model.dynamic])
    assert not torch.allclose(moved[model.dynamic], still[model.dynamic])


@pytest.mark.parametrize("share", [0.0, 0.5, 0.3, 1.0])
def test_frontier_steps_train_on_the_newest_times_of_the_ramp(
    tmp_path: Path, share: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    # 40 steps: a warm-up of 2, then the window widens over 20 and is full from step 22.
    trainer = tiny_trainer(
        tmp_path, max_iters=40, warmup_iters=2, time_ramp=0.5, frontier_share=share
    )
    frontier = [s for s in range(40) if schedules.is_frontier_step(trainer.config, s)]
    assert all(2 <= s < 22 for s in frontier)
    assert len(frontier) == round(20 * share)  # spread evenly over the ramp's 20 steps
    if share != 0.5:
        return
    assert frontier == list(range(3, 22, 2))
    # Training: the frontier steps, and they alone, draw from the newest part of the window.
    times = sorted(set(trainer.data.scene.train.times.tolist()))
    span = trainer.config.frontier_span
    draws: list[tuple[int, float, float]] = []
    next_views = trainer.data.next_views
    view_times = trainer.data.scene.train.times.tolist()

    def recorded(window: float, frontier_span: float | None = None) -> list[int]:
        picks = next_views(window, frontier_span)
        if frontier_span is not None:
            draws.extend((trainer.step, window, view_times[i]) for i in picks)
        return picks

    monkeypatch.setattr(trainer.data, "next_views", recorded)
    while trainer.step < 24:
        trainer.train_step(trainer.step)
        trainer.step += 1
    assert [step for step, _, _ in draws] == frontier
    for _, window, time in draws:
        latest = max(t for t in times if t <= window)
        assert min(window - span, latest) <= time <= window


@pytest.mark.parametrize("jitter", [0.0, 0.5])
def test_views_are_drawn_at_jittered_times_that_settle_on_the_view_time(
    tmp_path: Path, jitter: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Annealed smooth training: the model is drawn at the view's time plus noise whose
    # deviation is jitter × the times' spacing × (1 − progress), clamped to [0, 1].
    trainer = tiny_trainer(tmp_path, max_iters=30, time_jitter=jitter)
    times = sorted(set(trainer.data.scene.train.times.tolist()))
    spacing = trainer.data.time_spacing
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert max(gaps) - min(gaps) < 1e-6 and spacing == pytest.approx(gaps[0], rel=1e-6)
    asked: list[float] = []
    at = trainer.model.at

    def drawn(t: float, **options):  # type: ignore[no-untyped-def]
        asked.append(t)
        return at(t, **options)

    monkeypatch.setattr(trainer.model, "at", drawn)
    batches: list[float] = []
    train_batch = trainer.data.train_batch

    def recorded(index: int):  # type: ignore[no-untyped-def]
        batch = train_batch(index)
        batches.append(batch.time)
        return batch

    monkeypatch.setattr(trainer.data, "train_batch", recorded)
    for step in range(30):
        trainer.train_step(step)
    shifts = [a - b for a, b in zip(asked, batches, strict=True)]
    assert all(0.0 <= t <= 1.0 for t in asked)
    if jitter == 0:  # no noise, and no draw from the run's generator for it
        assert shifts == [0.0] * 30
        state = trainer.generator.get_state()
        assert time_noise(trainer.config, 0, spacing, trainer.generator) == [0.0]
        assert torch.equal(trainer.generator.get_state(), state)
        return
    for step, shift in enumerate(shifts):  # within 5 deviations of its step's scale
        scale = schedules.time_jitter(trainer.config, step) * spacing
        assert abs(shift) <= 5 * scale + 1e-7
    assert sum(abs(d) > 1e-6 for d in shifts[:10]) >= 8  # early steps do move
    assert max(abs(d) for d in shifts[:10]) > max(abs(d) for d in shifts[-3:])
    assert schedules.time_jitter(trainer.config, 0) == jitter
    assert schedules.time_jitter(trainer.config, 30) == 0.0


def test_time_jitter_is_checked() -> None:
    from dyngs.errors import ConfigError

    with pytest.raises(ConfigError, match="--time-jitter"):
        tiny_config(time_jitter=-0.1)


def test_frontier_settings_are_checked() -> None:
    from dyngs.errors import ConfigError

    with pytest.raises(ConfigError, match="--frontier-share must be in"):
        tiny_config(frontier_share=1.5)
    with pytest.raises(ConfigError, match="--frontier-span must be in"):
        tiny_config(frontier_span=0.0)


def test_importance_is_the_largest_share_of_any_view_of_the_window(tmp_path: Path) -> None:
    """measure_importance against a brute-force loop over every training view with
    t ≤ window."""
    trainer = tiny_trainer(tmp_path, max_iters=40, warmup_iters=2, time_ramp=0.5)
    step = 12  # the window is part-way open
    window = schedules.time_window(trainer.config, step)
    split = trainer.data.scene.train
    views = [i for i in range(len(split)) if float(split.times[i]) <= window]
    assert 0 < len(views) < len(split)
    expected = torch.zeros(len(trainer.model.canonical))
    renderer = trainer.renderer
    assert isinstance(renderer, ContributionRenderer)
    with torch.no_grad():
        for i in views:
            gaussians = trainer.model.at(float(split.times[i]))
            out = renderer.with_contribution(gaussians, split.cameras[i], trainer.data.background)
            assert out.contribution is not None
            expected = torch.maximum(expected, out.contribution)
    assert expected.max() > 0.5 > expected.min()  # both sides of the threshold occur
    times: list[float] = []
    deform = trainer.model.at

    def counted(t: float, absent_below: float = 0.0) -> Gaussians:
        times.append(t)
        return deform(t, absent_below=absent_below)

    trainer.model.at = counted  # type: ignore[method-assign, assignment]
    torch.testing.assert_close(
        trainer.lifecycle.measure_importance(step, trainer.renderer), expected, rtol=0, atol=1e-6
    )
    # One deformation a time, whatever number of cameras saw it (two a time here).
    distinct = {float(split.times[i]) for i in views}
    assert len(views) > len(distinct)
    assert sorted(times) == sorted(distinct)


@pytest.mark.parametrize("views", [0, 100])
def test_refinement_prunes_by_the_measured_importance(
    tmp_path: Path, views: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With --densify.importance-views > 0 a refinement prunes exactly the Gaussians the
    measure finds weak, whatever was drawn since the last one; with 0 it keeps the
    importance gathered from the drawn views."""
    densify = DensifyConfig(refine_start=0, refine_every=10, importance_views=views)
    trainer = tiny_trainer(tmp_path, max_iters=40, densify=densify)
    n = len(trainer.model.canonical)
    weak = torch.zeros(n, dtype=torch.bool)
    weak[::3] = True
    measured = torch.where(weak, 0.1, 5.0)
    monkeypatch.setattr(
        trainer.lifecycle, "measure_importance", lambda step, renderer: measured.clone()
    )
    state = trainer.lifecycle.state
    state.count.fill_(1)  # every Gaussian was seen; no gradient asks for growth
    drawn = torch.where(weak, 5.0, 0.1)  # what the drawn views said: the opposite
    state.importance.copy_(drawn)
    before = trainer.model.canonical.means.detach().clone()
    trainer.lifecycle.refine(10, trainer.optimizer, trainer.renderer)
    pruned = weak if views > 0 else drawn < densify.prune_importance
    assert torch.equal(trainer.model.canonical.means.detach(), before[~pruned])


def test_resume_is_bit_identical_on_cpu(tmp_path: Path) -> None:
    # Resumed halfway through the time ramp (steps 3-14), with frontier draws before and
    # after the checkpoint, from a span wide enough to hold several views.
    config = tiny_config(max_iters=16, warmup_iters=3, time_ramp=0.75, frontier_span=0.5)
    straight = Trainer(config, tmp_path / "a", NullWriter())
    for step in range(16):
        straight.train_step(step)

    first = Trainer(config, tmp_path / "b", NullWriter())
    for step in range(6):
        first.train_step(step)
        first.step = step + 1
    first.save()
    resumed = Trainer(config, tmp_path / "b", NullWriter())
    resumed.load(first.checkpoint_path())
    assert resumed.step == 6
    for step in range(6, 16):
        resumed.train_step(step)

    assert_same_state(straight.model.state_dict(), resumed.model.state_dict())


@pytest.mark.slow
def test_real_scene_loss_falls_and_psnr_rises(tmp_path: Path) -> None:
    """A short run on ../shared/data/lego-tiny (100², black background)."""
    path = shared_scene("lego-tiny")
    config = tiny_config(
        data=str(path),
        max_iters=150,
        warmup_iters=50,
        dataset=DataConfig(background=(0.0, 0.0, 0.0)),
    )
    trainer = Trainer(config, tmp_path, NullWriter())
    view = next(iter(trainer.data.views("train")))

    def quality() -> float:
        with torch.no_grad():
            out = trainer.renderer(
                trainer.model.at(view.time, sh_degree=0), view.camera, trainer.data.background
            )
        return float(psnr(out.rgb, view.image))

    before = quality()
    losses = [float(trainer.train_step(step).loss) for step in range(config.steps)]
    after = quality()
    assert sum(losses[-20:]) < 0.7 * sum(losses[:20])
    assert after > before + 3.0, (before, after)
    assert torch.isfinite(trainer.model.canonical.means).all()


@pytest.mark.parametrize("name", ["config", "checkpoint"])
def test_unreadable_run_files_say_which(tmp_path: Path, name: str) -> None:
    from dyngs.configio import load_config
    from dyngs.engine.checkpoint import load_checkpoint
    from dyngs.errors import ConfigError

    path = tmp_path / f"{name}.bin"
    path.write_bytes(b"\x00garbage")
    with pytest.raises(ConfigError, match=str(path)):
        (load_config if name == "config" else load_checkpoint)(path)


@pytest.mark.parametrize("views", [0, 100])
def test_the_importance_pass_is_timed_and_survives_resume(tmp_path: Path, views: int) -> None:
    densify = dataclasses.replace(
        tiny_config().densify, refine_start=0, refine_every=4, importance_views=views
    )
    trainer = tiny_trainer(tmp_path, densify=densify, max_iters=9)
    for step in range(trainer.config.steps):
        trainer.train_step(step)
        trainer.step = step + 1
    spent = trainer.lifecycle.importance_seconds
    # Two refinements (steps 4 and 8) measured, or none with the drawn views deciding.
    assert (spent > 0) == (views > 0)
    assert trainer.evaluate()["importance_seconds"] == spent  # reported in metrics.json
    trainer.save()
    resumed = tiny_trainer(tmp_path, densify=densify, max_iters=9)
    resumed.load(trainer.checkpoint_path())
    assert resumed.lifecycle.importance_seconds == spent


def test_hooks_see_every_step_in_order(tmp_path: Path) -> None:
    seen: list[tuple[int, bool]] = []
    config = tiny_config(max_iters=3, warmup_iters=1)
    trainer = Trainer(
        config, tmp_path, NullWriter(), hooks=[lambda t, s: seen.append((t.step, s.applied))]
    )
    trainer.train()
    assert seen == [(1, True), (2, True), (3, True)]

from __future__ import annotations

import copy
import math
from pathlib import Path

import pytest
import torch
from torch import nn

from dyngs.engine import schedules
from dyngs.engine.optim import (
    OptimConfig,
    build_optimizer,
    deformation_rate_scale,
    replace_rows,
    set_learning_rates,
)
from dyngs.errors import ConfigError
from tests.engine.helpers import tiny_trainer


def test_groups_and_exponential_decay(tmp_path: Path) -> None:
    trainer = tiny_trainer(tmp_path)
    groups = {g["name"]: g for g in trainer.optimizer.param_groups}
    assert set(groups) == {
        "means",
        "quats",
        "log_scales",
        "opacity_logits",
        "sh_dc",
        "sh_rest",
        "time_centers",
        "time_log_scales",
        "grid",
        "network",
    }
    # Every parameter of the model is optimised, exactly once.
    optimised = [p for g in trainer.optimizer.param_groups for p in g["params"]]
    assert (
        len(optimised) == len({id(p) for p in optimised}) == len(list(trainer.model.parameters()))
    )

    means = groups["means"]
    start, end = means["lr_start"], means["lr_end"]
    assert start == pytest.approx(1.6e-4 * trainer.extent)
    set_learning_rates(trainer.optimizer, 0.0)
    assert means["lr"] == pytest.approx(start)
    set_learning_rates(trainer.optimizer, 0.5)
    assert means["lr"] == pytest.approx(math.sqrt(start * end))
    set_learning_rates(trainer.optimizer, 1.0)
    assert means["lr"] == pytest.approx(end)
    assert groups["quats"]["lr"] == pytest.approx(1e-3)  # constant groups stay put


def test_deformation_rates_hold_until_the_time_window_is_full(tmp_path: Path) -> None:
    # 100 steps: a warm-up of 10, then the window widens over 40 and is full at step 50.
    held = OptimConfig(hold_deformation_rates=True)
    trainer = tiny_trainer(tmp_path, max_iters=100, warmup_iters=10, time_ramp=0.4, optim=held)
    groups = {g["name"]: g for g in trainer.optimizer.param_groups}
    means, grid, network = groups["means"], groups["grid"], groups["network"]
    assert schedules.window_full_step(trainer.config) == 50
    assert (
        schedules.time_window(trainer.config, 49) < 1.0
        and schedules.time_window(trainer.config, 50) == 1.0
    )

    def rates_at(step: int) -> tuple[float, float, float]:
        set_learning_rates(trainer.optimizer, *schedules.learning_progress(trainer.config, step))
        return means["lr"], grid["lr"], network["lr"]

    for step in (0, 30, 50):  # the Gaussians decay from step 0, the deformation holds
        m, g, n = rates_at(step)
        assert m == pytest.approx(
            means["lr_start"] * (means["lr_end"] / means["lr_start"]) ** (step / 100)
        )
        assert (g, n) == pytest.approx((grid["lr_start"], network["lr_start"]), rel=1e-12)
    _, g, n = rates_at(75)  # halfway through the rest of the run
    assert g == pytest.approx(math.sqrt(grid["lr_start"] * grid["lr_end"]))
    assert n == pytest.approx(math.sqrt(network["lr_start"] * network["lr_end"]))
    assert rates_at(100)[1:] == pytest.approx((grid["lr_end"], network["lr_end"]))

    # By default every group decays over the whole run (the schedule of 4DGaussians).
    plain = tiny_trainer(tmp_path / "plain", max_iters=100, warmup_iters=10, time_ramp=0.4)
    set_learning_rates(plain.optimizer, *schedules.learning_progress(plain.config, 30))
    plain_grid = next(g for g in plain.optimizer.param_groups if g["name"] == "grid")
    assert plain_grid["lr"] == pytest.approx(
        plain_grid["lr_start"] * (plain_grid["lr_end"] / plain_grid["lr_start"]) ** 0.3
    )


def test_a_longer_run_moves_the_deformation_in_smaller_steps() -> None:
    sized = OptimConfig(deformation_steps=3000, deformation_floor=0.3)
    assert deformation_rate_scale(sized, 1500) == deformation_rate_scale(sized, 3000) == 1.0
    assert deformation_rate_scale(sized, 6000) == pytest.approx(0.5)  # rate × steps held
    assert deformation_rate_scale(sized, 9000) == pytest.approx(1 / 3)
    assert deformation_rate_scale(sized, 40_000) == 0.3  # never below the floor
    fixed = OptimConfig(deformation_steps=None)
    assert deformation_rate_scale(fixed, 40_000) == 1.0
    for bad in ({"deformation_steps": 0}, {"deformation_floor": 0.0}, {"deformation_floor": 2.0}):
        with pytest.raises(ConfigError, match=r"--optim\.deformation-"):
            OptimConfig(**bad)


def test_the_scale_reaches_the_deformation_groups_alone(tmp_path: Path) -> None:
    # 200 steps where the rates are those of 50: the deformation learns at a quarter.
    optim = OptimConfig(deformation_steps=50, deformation_floor=0.1)
    trainer = tiny_trainer(tmp_path, max_iters=200, optim=optim)
    plain = tiny_trainer(tmp_path / "plain", max_iters=200)
    for step in (0, 100, 200):
        set_learning_rates(trainer.optimizer, *schedules.learning_progress(trainer.config, step))
        set_learning_rates(plain.optimizer, *schedules.learning_progress(plain.config, step))
        for scaled, unscaled in zip(
            trainer.optimizer.param_groups, plain.optimizer.param_groups, strict=True
        ):
            share = 0.25 if scaled["name"] in ("grid", "network") else 1.0
            assert scaled["lr"] == pytest.approx(share * unscaled["lr"], rel=1e-12)
    # The run says so before its first step, and a budget's re-plan says the new share.
    assert any("0.25× --optim.grid" in note for note in trainer.notes())
    assert not any("--optim.grid" in note for note in plain.notes())


def test_replace_rows_moves_and_zeroes_moments() -> None:
    old = nn.Parameter(torch.arange(8.0).reshape(4, 2))
    optimizer = torch.optim.Adam([old], lr=0.1)
    old.grad = torch.ones_like(old)
    optimizer.step()
    before = {k: v.clone() for k, v in optimizer.state[old].items()}

    source = torch.tensor([3, 0, 0])
    fresh = torch.tensor([False, False, True])
    new = nn.Parameter(old.detach()[source].clone())
    replace_rows(optimizer, old, new, source, fresh)

    assert optimizer.param_groups[0]["params"][0] is new
    state = optimizer.state[new]
    assert torch.equal(state["exp_avg"][:2], before["exp_avg"][source[:2]])
    assert torch.equal(state["exp_avg_sq"][2], torch.zeros(2))
    assert torch.equal(state["step"], before["step"])  # scalar state is shared, not per row
    assert old not in optimizer.state


def test_the_fused_adam_follows_the_per_tensor_adam(tmp_path: Path) -> None:
    """On the CPU the optimizer is PyTorch's fused Adam kernel; the per-tensor Adam
    (`--optim.no-fused`) is its reference. Two copies of a model, one under each, given the
    same gradients, learning rates and row surgery, end where the other does up to float32
    rounding."""
    trainer = tiny_trainer(tmp_path)
    assert trainer.optimizer.defaults["fused"] is True
    models = [trainer.model, copy.deepcopy(trainer.model)]
    fused = build_optimizer(models[0], OptimConfig(), trainer.extent)
    reference = build_optimizer(models[1], OptimConfig(fused=False), trainer.extent)
    assert fused.defaults["fused"] and not reference.defaults["fused"]
    generator = torch.Generator().manual_seed(0)
    for step in range(30):
        grads = [torch.randn(p.shape, generator=generator) for p in models[0].parameters()]
        for model, optimizer in zip(models, (fused, reference), strict=True):
            set_learning_rates(optimizer, step / 30)
            for p, g in zip(model.parameters(), grads, strict=True):
                p.grad = g.clone()
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        if step == 10:  # a densification's row surgery between steps
            n = len(models[0].canonical)
            source = torch.cat((torch.arange(n), torch.arange(3)))
            fresh = torch.arange(len(source)) >= n
            for model, optimizer in zip(models, (fused, reference), strict=True):
                old = model.canonical.means
                new = nn.Parameter(old.detach()[source].clone())
                replace_rows(optimizer, old, new, source, fresh)
                model.canonical.means = new
    for (name, a), b in zip(models[0].named_parameters(), models[1].parameters(), strict=True):
        assert a.shape == b.shape, name
        scale = max(float(b.detach().abs().max()), 1e-6)
        assert float((a - b).detach().abs().max()) <= 1e-5 * scale, name

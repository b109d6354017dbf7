from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from torch import nn

from dyngs.engine.optim import replace_rows, set_learning_rates
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

"""benchmarks/profile_step.py's timing of one method inside a training step."""

from __future__ import annotations

import pytest
import torch

from dyngs.compiled import kernel_times
from dyngs.losses.photometric import ssim_map
from tests.tools.conftest import load_benchmark


class Counter:
    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def step(self, *args: object, **kwargs: object) -> str:
        self.calls.append((args, kwargs))
        return "stepped"


def test_time_calls_times_each_call_and_changes_none() -> None:
    profile_step = load_benchmark("profile_step")
    counter = Counter()
    seconds = profile_step.time_calls(counter, "step")
    assert seconds == []
    assert counter.step(1, lr=2) == "stepped"
    assert counter.step() == "stepped"
    assert counter.calls == [((1,), {"lr": 2}), ((), {})]
    assert len(seconds) == 2 and all(s >= 0.0 for s in seconds)


def test_kernel_launches_are_timed_only_inside_the_block() -> None:
    pytest.importorskip("numba")
    gen = torch.Generator().manual_seed(0)
    pred, target = torch.rand(2, 24, 20, 3, generator=gen)
    ssim_map(pred, target)  # compiles (or loads) its kernels outside the block
    with kernel_times() as launches:
        ssim_map(pred, target)
        ssim_map(pred, target)
    assert launches["ssim_forward"] and len(launches["ssim_forward"]) == 2
    assert all(seconds >= 0.0 for times in launches.values() for seconds in times)
    counted = {name: len(times) for name, times in launches.items()}
    ssim_map(pred, target)  # after the block: not recorded
    assert {name: len(times) for name, times in launches.items()} == counted


def test_kernels_per_step_averages_over_steps_costliest_first() -> None:
    profile_step = load_benchmark("profile_step")
    rows = profile_step.kernels_per_step({"a": [0.001, 0.003], "b": [0.010]}, steps=2)
    assert list(rows) == ["b", "a"]
    assert rows["a"] == pytest.approx({"ms": 2.0, "calls": 1.0, "median_call_ms": 2.0})
    assert rows["b"] == pytest.approx({"ms": 5.0, "calls": 0.5, "median_call_ms": 10.0})

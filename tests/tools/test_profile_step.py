"""benchmarks/profile_step.py's timing of one method inside a training step."""

from __future__ import annotations

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

"""benchmarks/time_compositing.py: it times both launches of every render and counts the
forward kernel's work."""

from __future__ import annotations

import pytest

from tests.tools.conftest import load_benchmark

pytest.importorskip("numba")
time_compositing = load_benchmark("time_compositing")
make_scene = time_compositing.make_scene


def test_times_both_launches_and_counts_visits() -> None:
    r = time_compositing.time_case(*make_scene(300, 40, 2.0), threads=1, repeats=2)
    assert len(r["forward_runs_ms"]) == len(r["backward_runs_ms"]) == 2
    assert all(ms > 0 for ms in r["forward_runs_ms"] + r["backward_runs_ms"])
    # Every pair drawn was visited; a scene this dense draws most of what it visits.
    assert 0 < r["pairs_drawn"] <= r["visits"]
    assert r["forward_ns_per_visit"] == pytest.approx(r["forward_ms"] * 1e6 / r["visits"])

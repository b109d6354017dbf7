"""benchmarks/bench_renderer.py: the steady peak counts what is allocated after the reset,
and not what was allocated and freed before it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.tools.conftest import load_benchmark

bench_renderer = load_benchmark("bench_renderer")


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="needs Linux /proc")
def test_steady_peak_sees_only_what_follows_the_reset() -> None:
    before = np.ones(64 * 2**20 // 8)  # 64 MiB touched, then freed: the one-off peak
    del before
    base = bench_renderer._reset_peak_rss()
    if base is None:
        pytest.skip("this kernel does not let a process reset its peak RSS")
    assert bench_renderer._status_kb("VmHWM") - base < 16 * 1024
    # 48 MiB touched after the reset: above glibc's largest mmap threshold (32 MiB), so it
    # is fresh pages whatever the allocator kept from before.
    after = np.ones(48 * 2**20 // 8)
    assert bench_renderer._status_kb("VmHWM") - base >= 46 * 1024
    del after

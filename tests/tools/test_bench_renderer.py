"""benchmarks/bench_renderer.py: the steady peak counts what is touched after the reset,
and not what was touched and given back before it."""

from __future__ import annotations

import mmap
from pathlib import Path

import pytest

from tests.tools.conftest import load_benchmark

bench_renderer = load_benchmark("bench_renderer")

MIB = 2**20


def _touch(size: int) -> mmap.mmap:
    """`size` bytes of fresh anonymous memory, every page written: RSS the allocator cannot
    have served from memory the process already holds (as malloc may, in a long test run)."""
    block = mmap.mmap(-1, size)
    for offset in range(0, size, mmap.PAGESIZE):
        block[offset] = 1
    return block


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="needs Linux /proc")
def test_steady_peak_sees_only_what_follows_the_reset() -> None:
    _touch(64 * MIB).close()  # the one-off peak, given back before the reset
    base = bench_renderer._reset_peak_rss()
    if base is None:
        pytest.skip("this kernel does not let a process reset its peak RSS")
    assert bench_renderer._status_kb("VmHWM") - base < 16 * 1024
    after = _touch(32 * MIB)
    assert bench_renderer._status_kb("VmHWM") - base >= 30 * 1024
    after.close()

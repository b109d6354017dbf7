"""benchmarks/bench_renderer.py: the steady peak counts what is touched after the reset,
and not what was touched and given back before it; scene files read back what was saved."""

from __future__ import annotations

import mmap
from pathlib import Path

import pytest
import torch

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


def test_a_saved_scene_reads_back_as_it_was(tmp_path: Path) -> None:
    scene, camera = bench_renderer.make_scene(50, 24, 1.5)
    camera = camera.__class__(300.0, 310.0, 11.5, 13.0, camera.world_to_camera, 24, 30)
    path = tmp_path / "scene.npz"
    bench_renderer.save_scene(path, scene, camera)
    loaded, again = bench_renderer.load_scene_file(path)
    for name in bench_renderer.SCENE_ARRAYS:
        assert torch.equal(getattr(loaded, name), getattr(scene, name).float()), name
    assert (again.fx, again.fy, again.cx, again.cy) == (300.0, 310.0, 11.5, 13.0)
    assert (again.width, again.height) == (24, 30)
    assert torch.equal(again.world_to_camera, camera.world_to_camera.float())


def test_speedups_are_the_reference_time_over_each_renderers() -> None:
    rows: list[dict] = [
        {"case": "c", "renderer": "cpu-tile", "total_ms": 5.0},
        {"case": "c", "renderer": "cpu-reference", "total_ms": 40.0},
        {"case": "c", "renderer": "peer", "error": "failed"},
    ]
    bench_renderer.add_speedups(rows)
    assert rows[0]["speedup_vs_reference"] == 8.0
    assert rows[1]["speedup_vs_reference"] == 1.0
    assert "speedup_vs_reference" not in rows[2]
    alone: list[dict] = [{"case": "c", "renderer": "cpu-tile", "total_ms": 5.0}]
    bench_renderer.add_speedups(alone)  # no reference timed: nothing to compare with
    assert "speedup_vs_reference" not in alone[0]


def test_speedups_by_round_pair_each_round_with_its_own_reference() -> None:
    reference = [{"total_s": [0.040, 0.050, 0.060]}, {"error": "failed"}, {"total_s": [0.090]}]
    own = [{"total_s": [0.005, 0.006, 0.004]}, {"total_s": [0.005]}, {"total_s": [0.010]}]
    # Round 1: 0.050 / 0.005; round 2 has no reference time; round 3: 0.090 / 0.010.
    assert bench_renderer.round_speedups(reference, own) == pytest.approx([10.0, 9.0])
    with pytest.raises(ValueError):  # the rounds of the two must line up
        bench_renderer.round_speedups(reference, own[:2])

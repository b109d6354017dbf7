"""The process settings every dyngs-* tool applies (dyngs/tools/common.py)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

from dyngs.tools import common

# Four 4 MB arrays made and freed together, as a training step makes and frees its
# activations: by default glibc hands the freed top of its heap back to the system once it
# exceeds twice its (adaptive) mmap threshold, and the next step takes it back page by page.
_CHILD = textwrap.dedent(
    """
    import json, resource
    import numpy as np
    from dyngs.tools.common import keep_freed_memory

    def faults():
        return resource.getrusage(resource.RUSAGE_THREAD).ru_minflt

    def step():
        arrays = [np.ones(500_000) for _ in range(4)]
        del arrays

    def per_step():  # the quietest of five rounds: the kernel may reclaim pages meanwhile
        step(); step()
        rounds = []
        for _ in range(5):
            before = faults()
            for _ in range(4):
                step()
            rounds.append((faults() - before) / 4)
        return min(rounds)

    default = per_step()
    kept = keep_freed_memory()
    print(json.dumps({"default": default, "kept": kept, "after": per_step()}))
    """
)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="page-fault counts: Linux")
def test_kept_memory_is_reused_without_page_faults() -> None:
    done = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True,
                          check=True)  # fmt: skip
    counts = json.loads(done.stdout)
    if not counts["kept"]:
        pytest.skip("this C library has no mallopt (not glibc)")
    # 16 MB is ~3 900 pages; by default a step faults in most of them again.
    assert counts["default"] > 1000, counts
    assert counts["after"] < 5, counts


def test_every_tool_keeps_freed_memory(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[int] = []

    def counted() -> bool:
        calls.append(1)
        return True

    monkeypatch.setattr(common, "keep_freed_memory", counted)
    common.run_tool(lambda console: None)
    assert calls == [1]

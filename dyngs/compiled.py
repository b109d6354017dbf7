"""Running compiled (numba) kernels: one launch at a time, on a chosen number of threads,
and a line on stderr the first time a process has to compile one.

Launches are serialised: numba's fallback threading layer (workqueue) must not be entered
from two threads at once (the web viewer renders from its own thread while training
runs), and two launches would only share the cores anyway. Kernels are compiled on first
use and cached on disk (numba's cache, next to their module or under NUMBA_CACHE_DIR).
"""

from __future__ import annotations

import importlib.util
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import torch

_LOCK = threading.Lock()
_COMPILED: set[str] = set()
_TIMES: dict[str, list[float]] | None = None


@contextmanager
def kernel_times() -> Iterator[dict[str, list[float]]]:
    """Within the block, each kernel launch's wall time (seconds) is appended to the list
    under its kernel's name, for profiling: the kernels timed where they run, without a
    profiler's overhead, which inflates some operators far more than others."""
    global _TIMES
    times: dict[str, list[float]] = {}
    _TIMES = times
    try:
        yield times
    finally:
        _TIMES = None


def numba_available() -> bool:
    """Whether numba, which compiles the kernels, is installed."""
    return importlib.util.find_spec("numba") is not None


def noalias_option() -> dict[str, Any]:
    """`{"noalias": True}`, for `njit(**noalias_option())`, where this numba can mark a
    function's array arguments `noalias` (LLVM's `restrict`); `{}` where it cannot.

    numba lowers a function with that flag so (it has it internally, for parallel
    regions) but has no decorator option for it (numba PR 9108, abandoned): this maps one.
    Without it LLVM cannot tell two arrays apart, and before a loop that writes one and
    reads another it checks at run time that they do not overlap, on every entry to the
    loop. Only for functions whose array arguments truly never share memory: an overlap
    is then undefined behaviour, not a slow path."""
    from numba.core import compiler, cpu, options

    if not hasattr(compiler.Flags, "noalias"):
        return {}
    if not hasattr(cpu.CPUTargetOptions, "noalias"):
        mapping = options.TargetOptions.Mapping("noalias")
        cpu.CPUTargetOptions.noalias = mapping  # type: ignore[attr-defined]
    return {"noalias": True}


def thread_count(threads: int | None) -> int:
    """The configured threads (None: PyTorch's), within numba's pool."""
    import numba

    most = numba.config.NUMBA_NUM_THREADS  # type: ignore[attr-defined]  # set at import
    return max(1, min(threads or torch.get_num_threads(), most))


def run_kernel(kernel: Any, count: int, signature: str, *args: Any) -> None:
    """Run `kernel(*args)` on `count` threads; the first call of a process that has to
    compile it for `signature` (its argument types, in words) says so, and how long it
    took."""
    import numba

    key = f"{kernel.__name__}:{signature}"
    with _LOCK:
        torch_threads = torch.get_num_threads()
        numba.set_num_threads(count)
        if key in _COMPILED:
            started = time.perf_counter()
            kernel(*args)
            if _TIMES is not None:
                _TIMES.setdefault(kernel.__name__, []).append(time.perf_counter() - started)
        else:
            misses = sum(kernel.stats.cache_misses.values())
            started = time.perf_counter()
            kernel(*args)
            _COMPILED.add(key)
            if sum(kernel.stats.cache_misses.values()) > misses:
                sys.stderr.write(
                    f"[dyngs] compiled {kernel.__name__} for {signature} in "
                    f"{time.perf_counter() - started:.1f} s (cached on disk for later runs)\n"
                )
        # numba's OpenMP pool is PyTorch's (one libgomp): starting it with its own size
        # (all cores unless NUMBA_NUM_THREADS says otherwise) would change PyTorch's
        # thread count too, e.g. from the 1 of OMP_NUM_THREADS=1 to 2.
        if torch.get_num_threads() != torch_threads:
            torch.set_num_threads(torch_threads)

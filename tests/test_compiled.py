"""dyngs/compiled.py: launching numba kernels leaves PyTorch's thread count as it was."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
from typing import Any

_CHILD = textwrap.dedent(
    """
    import torch
    from kornia.filters import get_gaussian_kernel1d
    from dyngs.losses.photometric import gaussian_blur
    from dyngs.renderers.cpu_tile import CpuTileRenderer
    from dyngs.types import Camera, Gaussians

    before = torch.get_num_threads()
    gaussian_blur(torch.rand(1, 3, 16, 16), get_gaussian_kernel1d(11, 1.5))
    camera = Camera.from_fov(1.0, 16, 16, torch.eye(4))
    means = torch.tensor([[0.0, 0.0, 3.0]])
    scene = Gaussians(means, torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.2),
                      torch.tensor([0.5]), torch.full((1, 3), 0.5))
    CpuTileRenderer()(scene, camera, torch.zeros(3))
    print(before, torch.get_num_threads())
    """
)


def test_kernels_leave_pytorchs_thread_count_alone() -> None:
    # With OMP_NUM_THREADS=1 and no NUMBA_NUM_THREADS, numba sizes its pool to every core;
    # PyTorch shares that OpenMP runtime, and must still have one thread afterwards.
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_NUM_THREADS"}
    env["OMP_NUM_THREADS"] = "1"
    done = subprocess.run([sys.executable, "-c", _CHILD], env=env, capture_output=True,
                          text=True, check=True)  # fmt: skip
    assert done.stdout.split() == ["1", "1"], done.stdout


def test_noalias_option_marks_array_arguments_noalias() -> None:
    # The compositing kernels' per-tile loops take their pixel state as arguments marked
    # `noalias`, so that LLVM needs no overlap checks before each run of cells; the flag
    # is numba-internal, so check that it still reaches the compiled code.
    import numpy as np
    from numba import njit

    from dyngs.compiled import noalias_option

    option = noalias_option()
    assert option == {"noalias": True}

    def add(out: np.ndarray, a: np.ndarray) -> None:
        for i in range(out.shape[0]):
            out[i] += a[i]

    def data_pointer_is_noalias(kernel: Any) -> bool:
        kernel(np.zeros(4), np.ones(4))
        (ir,) = kernel.inspect_llvm().values()
        # `out` is passed as its fields; the fifth (index 4) is the pointer to its data.
        return re.search(r"ptr noalias [^,%]*%arg\.out\.4\b", ir) is not None

    assert data_pointer_is_noalias(njit(**option)(add))
    assert not data_pointer_is_noalias(njit(add))

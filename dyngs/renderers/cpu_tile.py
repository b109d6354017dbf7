"""`cpu-tile`: the fast path on CPUs, with compiled compositing kernels.

`prepare`, `project` and `bin_tiles` are the shared PyTorch stages (O(N), autograd does
their backward); compositing forward and backward are the numba kernels of
`dyngs.renderers.tile_kernels`, wrapped in one `torch.autograd.Function`, so gradients
reach the 2D means (which densification reads), conics, opacities, colours and depths,
and from there every Gaussian parameter. It is held to `cpu-reference`, the
specification, by tests/renderers/test_cpu_tile.py and the hard cases.

The kernels are compiled on first use and cached on disk (numba's cache, next to this
module or under NUMBA_CACHE_DIR); the first render of a process that has to compile says
so, and how long it took. Renders and gradients are the same on every run.

Letters: N Gaussians, M tile–Gaussian pairs, H×W image.
"""

from __future__ import annotations

import importlib.util
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from dyngs.errors import ConfigError, RendererUnavailable
from dyngs.renderers.base import Guards, RenderOutput
from dyngs.renderers.stages import TileBins, bin_tiles, finish_image, project
from dyngs.types import Camera, Gaussians


def cpu_tile_available() -> bool:
    """Whether numba, which compiles the kernels, is installed."""
    return importlib.util.find_spec("numba") is not None


@dataclass(frozen=True)
class CpuTileConfig:
    """The compiled tile rasterizer for CPUs (numba): the same image and gradients as
    cpu-reference, drawing only the pixels inside each Gaussian's α ≥ 1/255 ellipse."""

    tile_size: int = 16
    """Tile edge in pixels: the unit of parallel work and of early termination (a tile
    stops when all its pixels have). The image does not depend on it."""
    threads: int | None = None
    """Threads the kernels use; None: PyTorch's (`torch.get_num_threads()`)."""
    antialiased: bool = False
    """Mip-Splatting's 2D filter: scale opacity by √(det Σ / det(Σ + 0.3 I)) (Yu et al. 2024)."""

    def __post_init__(self) -> None:
        if self.tile_size < 1:
            raise ConfigError(f"--renderer.tile-size must be ≥ 1, got {self.tile_size}")
        if self.threads is not None and self.threads < 1:
            raise ConfigError(f"--renderer.threads must be ≥ 1 (or None), got {self.threads}")

    def build(self) -> CpuTileRenderer:
        return CpuTileRenderer(self)


class CpuTileRenderer:
    """`prepare` → `project` → `bin_tiles` in PyTorch, then the compiled kernels.
    `contribution=True` (or `with_contribution`) also measures each Gaussian's
    contribution."""

    def __init__(self, config: CpuTileConfig | None = None, guards: Guards | None = None):
        if not cpu_tile_available():
            raise RendererUnavailable(
                "renderer cpu-tile needs numba, which is not installed; run "
                "`pip install numba` or use renderer:cpu-reference"
            )
        self.config = config or CpuTileConfig()
        self.guards = guards or Guards()
        self.last_work: np.ndarray | None = None
        """Per busy tile of the last render: pixel visits and pairs drawn (benchmarks)."""

    def __call__(
        self,
        gaussians: Gaussians,
        camera: Camera,
        background: Float[Tensor, 3],
        *,
        contribution: bool = False,
    ) -> RenderOutput:
        if gaussians.means.device.type != "cpu":
            raise RendererUnavailable(
                f"renderer cpu-tile draws on the CPU, not {gaussians.means.device}; "
                "use renderer:cuda-tile on a GPU"
            )
        screen = project(gaussians, camera, self.guards, antialiased=self.config.antialiased)
        if screen.means2d.requires_grad:
            screen.means2d.retain_grad()
        size = (camera.width, camera.height, self.config.tile_size)
        bins = bin_tiles(screen, *size)
        features = torch.cat((screen.colors, screen.depths.to(screen.colors.dtype)[:, None]), 1)
        log_opacity = screen.opacities.clamp_min(1e-30).log()
        plan = _Plan(bins, size, self.guards, self.config.threads, contribution)
        inputs = (screen.means2d, screen.conics, log_opacity, features)
        sums, per_pair = _Composite.apply(*inputs, plan)
        self.last_work = plan.work
        rgb, alpha, depth = finish_image(sums, background)
        weights = None
        if contribution:
            summed = _per_gaussian(bins, per_pair.numpy()[:, None], len(features))
            weights = torch.from_numpy(summed[:, 0]).to(screen.colors.dtype)
        return RenderOutput(
            rgb=rgb,
            alpha=alpha,
            depth=depth,
            means2d=screen.means2d,
            radii=torch.where(screen.visible[:, None], screen.extents.ceil(), 0).int(),
            visible=screen.visible,
            num_nonfinite=screen.num_nonfinite,
            contribution=weights,
        )

    def with_contribution(
        self, gaussians: Gaussians, camera: Camera, background: Float[Tensor, 3]
    ) -> RenderOutput:
        """As a call, with each Gaussian's contribution measured (`ContributionRenderer`)."""
        return self(gaussians, camera, background, contribution=True)


@dataclass
class _Plan:
    """Everything the kernels need besides the per-Gaussian tensors."""

    bins: TileBins
    size: tuple[int, int, int]
    """Width, height, tile size."""
    guards: Guards
    threads: int | None
    contribution: bool
    work: np.ndarray | None = None
    """After the forward: per busy tile, the pixel visits and the pairs drawn."""

    def tile_order(self) -> np.ndarray:
        """The tiles with any Gaussian, busiest first (by Gaussian count): dealt to the
        threads in turn, they share the work about evenly."""
        counts = self.bins.tile_count
        busy = (counts > 0).nonzero().squeeze(1)
        return busy[torch.argsort(counts[busy], descending=True, stable=True)].numpy()

    def layout(self) -> tuple[int, int, int, int]:
        """(tiles across, tile size, width, height), as the kernels take it."""
        width, height, tile = self.size
        return -(-width // tile), tile, width, height

    def limits(self) -> tuple[float, float, float]:
        """(α floor, α ceiling, transmittance floor), as the kernels take them."""
        g = self.guards
        return g.alpha_min, g.alpha_max, g.transmittance_min


# Kernel launches are serialised: numba's fallback threading layer (workqueue) must not be
# entered from two threads at once, and two renders would only share the cores anyway.
_LOCK = threading.Lock()
_COMPILED: set[str] = set()


def _launch(kernel: Any, threads: int | None, *args: Any) -> None:
    """Run a kernel with the configured thread count; the first call of a process that
    has to compile it says so, and how long it took."""
    import numba

    most = numba.config.NUMBA_NUM_THREADS  # type: ignore[attr-defined]  # set at import
    count = max(1, min(threads or torch.get_num_threads(), most))
    key = f"{kernel.__name__}:{args[0][3].dtype}"
    with _LOCK:
        numba.set_num_threads(count)
        if key in _COMPILED:
            kernel(*args, count)
            return
        misses = sum(kernel.stats.cache_misses.values())
        started = time.perf_counter()
        kernel(*args, count)
        _COMPILED.add(key)
        if sum(kernel.stats.cache_misses.values()) > misses:
            sys.stderr.write(
                f"[cpu-tile] compiled {kernel.__name__} for {args[0][3].dtype} in "
                f"{time.perf_counter() - started:.1f} s (cached on disk for later runs)\n"
            )


def _per_gaussian(bins: TileBins, per_pair: np.ndarray, count: int) -> np.ndarray:
    """Per-pair rows summed per Gaussian, in pair order."""
    from dyngs.renderers import tile_kernels

    out = np.zeros((count, per_pair.shape[1]))
    tile_kernels.sum_pairs(bins.gaussian.numpy(), np.ascontiguousarray(per_pair), out)
    return out


def _numpy(tensor: Tensor) -> np.ndarray:
    return tensor.detach().contiguous().numpy()


class _Composite(torch.autograd.Function):
    """Compositing of projected Gaussians as one differentiable operation: (2D means,
    conics, ln opacity, features r, g, b, depth) → per-pixel Σ w·(r, g, b, depth, 1)."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        means2d: Float[Tensor, "N 2"],
        conics: Float[Tensor, "N 3"],
        log_opacity: Float[Tensor, " N"],
        features: Float[Tensor, "N 4"],
        plan: _Plan,
    ) -> tuple[Float[Tensor, "H W 5"], Float[Tensor, " M"]]:
        from dyngs.renderers import tile_kernels

        width, height, _ = plan.size
        bins = plan.bins
        scene = (
            *(_numpy(t) for t in (means2d, conics, log_opacity, features)),
            *(_numpy(t) for t in (bins.gaussian, bins.tile_start, bins.tile_count)),
        )
        order = plan.tile_order()
        sums = np.zeros((height, width, 5), dtype=scene[3].dtype)
        transmittance = np.ones((height, width))
        last = np.full((height, width), -1, dtype=np.int64)
        per_pair = np.zeros(len(scene[4]) if plan.contribution else 0)
        plan.work = np.zeros((len(order), 2), dtype=np.int64)
        _launch(tile_kernels.composite_forward, plan.threads, scene, order, plan.layout(),
                plan.limits(), sums, transmittance, last, per_pair, plan.work)  # fmt: skip
        ctx.plan = plan
        ctx.state = (scene, order, transmittance, last)
        contribution = torch.from_numpy(per_pair)
        ctx.mark_non_differentiable(contribution)
        return torch.from_numpy(sums), contribution

    @staticmethod
    def backward(  # type: ignore[override]
        ctx: Any, grad_sums: Tensor, _grad_contribution: Tensor | None
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, None]:
        from dyngs.renderers import tile_kernels

        plan: _Plan = ctx.plan
        scene, order, transmittance, last = ctx.state
        pair_grads = np.empty((len(scene[4]), tile_kernels.PAIR_GRADS))
        upstream = grad_sums.detach().to(torch.float64).contiguous().numpy()
        _launch(tile_kernels.composite_backward, plan.threads, scene, order, plan.layout(),
                plan.limits(), upstream, transmittance, last, pair_grads)  # fmt: skip
        grads = torch.from_numpy(_per_gaussian(plan.bins, pair_grads, len(scene[0])))
        feature_dtype = torch.from_numpy(scene[3][:0]).dtype
        return (
            grads[:, 0:2],
            grads[:, 2:5],
            grads[:, 5],
            grads[:, 6:10].to(feature_dtype),
            None,
        )

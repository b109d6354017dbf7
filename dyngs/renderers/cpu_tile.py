"""`cpu-tile`: the fast path on CPUs, with compiled compositing kernels.

Projection (`project_compiled`: `stages.project`'s geometry, forward and backward, in
`dyngs.renderers.project_kernels`), the view-dependent colours (`_Colors`: `sh.eval_sh`
in `dyngs.renderers.sh_kernels`), binning (`bin_tiles_compiled`, the same bins as
`stages.bin_tiles`) and compositing forward and backward are compiled (numba), each held
to its PyTorch specification. Compositing is in
`dyngs.renderers.tile_kernels`, wrapped in one `torch.autograd.Function`, so gradients
reach the 2D means (which densification reads), conics, opacities, colours and depths,
and from there every Gaussian parameter. It is held to `cpu-reference`, the
specification, by tests/renderers/test_cpu_tile.py and the hard cases.

The kernels are compiled on first use and cached on disk, and run one launch at a time
(`dyngs.compiled`); the first render of a process that has to compile says so, and how
long it took. Renders and gradients are the same on every run.

Letters: N Gaussians, M tile–Gaussian pairs, H×W image.
"""

from __future__ import annotations

import heapq
import math
import threading
import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from dyngs.compiled import numba_available, run_kernel, thread_count
from dyngs.errors import ConfigError, RendererUnavailable
from dyngs.renderers.base import AntialiasedConfig, Guards, RenderOutput
from dyngs.renderers.stages import (
    _EXTENT_ABSOLUTE_MARGIN,
    _EXTENT_RELATIVE_MARGIN,
    GEOMETRY_DTYPE,
    ScreenGaussians,
    TileBins,
    finish_image,
    off_axis_limits,
)
from dyngs.sh import eval_sh0
from dyngs.types import Camera, Gaussians


def cpu_tile_available() -> bool:
    """Whether numba, which compiles the kernels, is installed."""
    return numba_available()


LARGE_TILE, SMALL_TILE = 32, 16
"""The tile sizes `choose_tile_size` picks from (pixels a side)."""


def choose_tile_size(width: int, height: int) -> int:
    """`LARGE_TILE` where the image holds at least four such tiles each way, else
    `SMALL_TILE`.

    A Gaussian is composited once per tile it reaches, and each such pair pays a set-up
    (its rows and blocks solved from the conic) and the rounding of its footprint out to
    whole rows and eight-column blocks at the tile's edges: larger tiles make fewer pairs.
    But tiles are also what the threads share, and a small image has few of them: a 100²
    frame at 32 px holds nine whole tiles and seven slivers four pixels wide. Measured on
    trained models (docs/RENDERER.md, "Tiles of 32 pixels"), 32-px tiles composited
    128² and larger frames faster and 100² frames slower on two threads. Chosen from the
    image's size alone, so that a render and its gradients do not depend on the thread
    count."""
    return LARGE_TILE if min(width, height) >= 4 * LARGE_TILE else SMALL_TILE


@dataclass(frozen=True)
class CpuTileConfig(AntialiasedConfig):
    """The compiled tile rasterizer for CPUs (numba): the same image and gradients as
    cpu-reference, drawing only the pixels inside each Gaussian's α ≥ 1/255 ellipse."""

    tile_size: int | None = None
    """Tile edge in pixels: the unit of parallel work and of early termination (a tile
    stops when all its pixels have). The image does not depend on it. None: chosen from
    the image's size (`choose_tile_size`: 32 where both sides are at least 128 px, else
    16)."""
    threads: int | None = None
    """Threads the kernels use; None: PyTorch's (`torch.get_num_threads()`)."""

    def __post_init__(self) -> None:
        if self.tile_size is not None and self.tile_size < 1:
            raise ConfigError(f"--renderer.tile-size must be ≥ 1 (or None), got {self.tile_size}")
        if self.threads is not None and self.threads < 1:
            raise ConfigError(f"--renderer.threads must be ≥ 1 (or None), got {self.threads}")

    def build(self) -> CpuTileRenderer:
        return CpuTileRenderer(self)


class CpuTileRenderer:
    """Compiled projection, binning and compositing, held to `prepare` → `project` →
    `bin_tiles` → compositing of cpu-reference.
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
        screen = project_compiled(
            gaussians, camera, self.guards, self.config.antialiased, self.config.threads
        )
        if screen.means2d.requires_grad:
            screen.means2d.retain_grad()
        tile = self.config.tile_size or choose_tile_size(camera.width, camera.height)
        size = (camera.width, camera.height, tile)
        bins = bin_tiles_compiled(screen, *size)
        features = torch.cat((screen.colors, screen.depths.to(screen.colors.dtype)[:, None]), 1)
        log_opacity = screen.opacities.clamp_min(1e-30).log()
        absgrad = torch.zeros(len(features), 2, dtype=torch.float64)
        inputs = (screen.means2d, screen.conics, log_opacity, features)
        backward = torch.is_grad_enabled() and any(t.requires_grad for t in inputs)
        plan = _Plan(bins, size, self.guards, self.config.threads, contribution, backward, absgrad)
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
            radii=screen.extents.ceil().int(),  # extents are 0 where not visible
            visible=screen.visible,
            num_nonfinite=screen.num_nonfinite,
            contribution=weights,
            means2d_absgrad=plan.absgrad,
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
    backward: bool
    """Whether a backward may follow: without one, the forward keeps no per-pixel state
    for it (at 800², 10 MB of transmittance and last-pair indices)."""
    absgrad: Tensor | None = None
    """When given, the backward fills it with Σ over pixels of |∂L/∂means2d| per axis
    (`RenderOutput.means2d_absgrad`)."""
    work: np.ndarray | None = None
    """After the forward: per busy tile, the pixel visits and the pairs drawn."""

    def deal(self) -> tuple[np.ndarray, np.ndarray]:
        """The tiles with any Gaussian and the threads they go to: (order, bounds), thread
        j compositing order[bounds[j]:bounds[j + 1]], forward and backward alike (the α a
        thread keeps for the backward are in its own row).

        Busiest first to the least loaded thread (Graham's LPT rule), a tile's work taken
        as its Gaussian count. Dealt in turn instead, the demo's trained frames (10-12
        busy tiles, two threads) gave the busier thread 13-15 % more cells than the mean,
        against 6-8 % so (docs/RENDERER.md, "Tiles dealt by their work"). Which thread
        draws a tile changes nothing in the image or its gradients."""
        order = self.busiest_first()
        threads = thread_count(self.threads)
        owner = np.zeros(len(order), dtype=np.int64)
        if threads > 1:
            loads = [(0, j) for j in range(threads)]  # a heap of (work so far, thread)
            for i, count in enumerate(self.bins.tile_count.numpy()[order].tolist()):
                load, j = heapq.heappop(loads)
                owner[i] = j
                heapq.heappush(loads, (load + count, j))
        return grouped_by_thread(order, owner, threads)

    def busiest_first(self) -> np.ndarray:
        """The tiles with any Gaussian, by Gaussian count, the busiest first (ties in tile
        order)."""
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


def grouped_by_thread(
    order: np.ndarray, owner: np.ndarray, threads: int
) -> tuple[np.ndarray, np.ndarray]:
    """A deal as the kernels take it, (tiles, bounds): the tiles of `order` grouped by
    their `owner` thread, each group in `order`'s order, thread j's being
    tiles[bounds[j]:bounds[j + 1]]."""
    bounds = np.zeros(threads + 1, dtype=np.int64)
    np.cumsum(np.bincount(owner, minlength=threads), out=bounds[1:])
    return order[np.argsort(owner, kind="stable")], bounds


class _AlphaStore:
    """The arrays the forward keeps each pair's α in for the backward (`tile_kernels`'
    `kept`), one row per thread, reused from render to render.

    A row must hold the most its tiles could keep, a whole tile's cells for every pair,
    of which a render writes only a fraction, at the row's end (`tile_kernels`' `kept`).
    Such an array is virtual memory until written, its pages backed one fault at a time
    as they are; allocated afresh for every render, those faults cost more than the kept
    α save (docs/RENDERER.md). Reused, the pages a render writes are already there: the
    memory held is what the largest renders wrote, in up to `KEEP` arrays. A render's
    array is back in the store once its autograd graph is freed (for a training step,
    during the next step's forward), not before: a graph kept for a second backward
    keeps its own."""

    KEEP = 2

    def __init__(self) -> None:
        self._free: list[np.ndarray] = []
        self._lock = threading.Lock()

    def take(self, plan: _Plan, deal: tuple[np.ndarray, np.ndarray], dtype: np.dtype) -> np.ndarray:
        """An array [threads, capacity] for a render of `plan` whose tiles are dealt as
        `deal` (`_Plan.deal`; when no backward will follow, one tile's cells a thread,
        which each pair overwrites)."""
        from dyngs.renderers import tile_kernels

        order, bounds = deal
        threads = len(bounds) - 1
        tile = tile_kernels.tile_cells(plan.size[2])
        if not plan.backward:
            return np.empty((threads, tile), dtype=dtype)
        counts = np.concatenate(([0], np.cumsum(plan.bins.tile_count.numpy()[order])))
        most = int((counts[bounds[1:]] - counts[bounds[:-1]]).max())
        cells = max(most * tile, 1)
        with self._lock:
            for i, array in enumerate(self._free):
                if array.dtype == dtype and array.shape[0] == threads and array.shape[1] >= cells:
                    return self._free.pop(i)
        return np.empty((threads, 1 << (cells - 1).bit_length()), dtype=dtype)

    def give(self, array: np.ndarray) -> None:
        """Take `array` back for later renders, keeping the `KEEP` latest."""
        with self._lock:
            self._free.append(array)
            del self._free[: -self.KEEP]


_ALPHAS = _AlphaStore()


def _launch(kernel: Any, threads: int | None, *args: Any) -> None:
    """Run a compositing kernel (it takes the thread count last, to deal tiles)."""
    count = thread_count(threads)
    run_kernel(kernel, count, str(args[0][3].dtype), *args, count)


def project_compiled(
    gaussians: Gaussians,
    camera: Camera,
    guards: Guards,
    antialiased: bool = False,
    threads: int | None = None,
) -> ScreenGaussians:
    """`stages.project` with the geometry compiled (`project_kernels`) and the colours
    too (`_Colors`: `eval_sh` from the same float64 camera-relative means, as there)."""
    from dyngs.renderers import project_kernels as pk

    g = gaussians
    used = g.colors if g.sh_degree is None else g.colors[:, : (g.sh_degree + 1) ** 2]
    params = (g.means, g.quats, g.scales, g.opacities, used)
    rows = tuple(_numpy(t).reshape(len(t), math.prod(t.shape[1:])) for t in params)  # N = 0 too
    finite = torch.empty(len(g.means), dtype=torch.bool)
    scene = np.empty((pk.SCENE_ROWS, len(g.means)))
    dtypes = "/".join(str(t.dtype)[6:] for t in params)  # compiled once for each combination
    run_kernel(pk.gather_scene, thread_count(threads), dtypes, rows, scene, finite.numpy())
    nonfinite = len(finite) - int(np.count_nonzero(finite.numpy()))
    w2c = camera.world_to_camera.to(dtype=GEOMETRY_DTYPE)
    view = _View(camera, guards, antialiased, scene, finite.numpy(), w2c, thread_count(threads))
    means2d, conics, opacities, depths, extents, visible = _Project.apply(*params[:4], view)
    # Rows with a non-finite entry are zeroed (their gradients too); most renders have none.
    colors = torch.where(finite.view(-1, *[1] * (used.ndim - 1)), used, 0) if nonfinite else used
    if g.sh_degree is None:
        rgb = colors
    elif g.sh_degree == 0:
        rgb = eval_sh0(colors)  # no view direction needed
    else:
        means = torch.where(finite[:, None], g.means, 0) if nonfinite else g.means
        center = -w2c[:3, :3].T @ w2c[:3, 3]
        rgb = _Colors.apply(colors, means, center.numpy(), g.sh_degree, view.threads)
    return ScreenGaussians(
        means2d=means2d,
        conics=conics,
        opacities=opacities,
        depths=depths,
        colors=rgb,
        extents=extents,
        visible=visible,
        num_nonfinite=torch.tensor(nonfinite),
    )


class _Colors(torch.autograd.Function):
    """(SH coefficients [N, K, 3], means [N, 3]) → colours [N, 3] seen from the camera
    centre: `sh.eval_sh` of the float64 camera-relative means, compiled
    (`sh_kernels`); the gradients come back in each input's dtype."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, coeffs: Tensor, means: Tensor, center: np.ndarray, degree: int, threads: int
    ) -> Tensor:
        from dyngs.renderers import sh_kernels

        coeffs, means = coeffs.detach().contiguous(), means.detach().contiguous()
        rgb = torch.empty(len(coeffs), 3, dtype=coeffs.dtype)
        signature = f"{str(coeffs.dtype)[6:]}/{str(means.dtype)[6:]}"
        run_kernel(sh_kernels.sh_forward, threads, signature, coeffs.numpy(), means.numpy(),
                   center, degree, rgb.numpy())  # fmt: skip
        ctx.save_for_backward(coeffs, means)
        ctx.settings = (center, degree, threads, signature)
        return rgb

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        from dyngs.renderers import sh_kernels

        coeffs, means = ctx.saved_tensors
        center, degree, threads, signature = ctx.settings
        coeffs_grad = torch.empty_like(coeffs)
        means_grad = torch.empty(len(means) if ctx.needs_input_grad[1] else 0, 3,
                                 dtype=means.dtype)  # fmt: skip
        upstream = grad.to(coeffs.dtype).contiguous()
        run_kernel(sh_kernels.sh_backward, threads, signature, coeffs.numpy(), means.numpy(),
                   center, degree, upstream.numpy(), coeffs_grad.numpy(),
                   means_grad.numpy())  # fmt: skip
        return (coeffs_grad if ctx.needs_input_grad[0] else None,
                means_grad if ctx.needs_input_grad[1] else None, None, None, None)  # fmt: skip


class _View:
    """The camera and guards as the projection kernels take them."""

    def __init__(
        self,
        camera: Camera,
        guards: Guards,
        antialiased: bool,
        scene: np.ndarray,
        finite: np.ndarray,
        w2c: Tensor,
        threads: int,
    ) -> None:
        self.threads = threads
        fx, fy = camera.fx, camera.fy
        left, right, top, bottom = off_axis_limits(camera, guards)
        self.rotation = np.ascontiguousarray(w2c[:3, :3].numpy())
        self.translation = np.ascontiguousarray(w2c[:3, 3].numpy())
        self.intrinsics = np.array(
            [fx, fy, camera.cx, camera.cy, left, top, camera.width, camera.height, right, bottom],
            dtype=np.float64,
        )
        self.limits = np.array(
            [camera.near, camera.far, guards.dilation(antialiased), guards.alpha_min,
             guards.quat_eps, _EXTENT_RELATIVE_MARGIN, _EXTENT_ABSOLUTE_MARGIN],
            dtype=np.float64,
        )  # fmt: skip
        self.antialiased = antialiased
        self.scene = scene
        """The parameters as `project_kernels.gather_scene` laid them out."""
        self.finite = finite
        self.valid: np.ndarray | None = None
        """Rows the forward kept (backward treats the others' det as the constant 1)."""

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(rotation, translation, intrinsics, limits), as `project_kernels` takes them."""
        return self.rotation, self.translation, self.intrinsics, self.limits


class _Project(torch.autograd.Function):
    """(means, quaternions, scales, opacities) → (2D means, conics, opacities, depths), in
    float64, and the non-differentiable extents and visibility. The kernels read the
    parameters from `_View.scene` (float64, gathered from these tensors); the gradients
    come back in each parameter's dtype."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, view: _View
    ) -> tuple[Tensor, ...]:
        from dyngs.renderers import project_kernels as pk

        n = len(means)
        out = tuple(np.empty((n, k) if k > 1 else n) for k in pk.OUT_COLUMNS)
        valid, visible = np.empty(n, dtype=np.bool_), np.empty(n, dtype=np.bool_)
        run_kernel(pk.project_forward, view.threads, "float64", view.scene, view.finite,
                   view.arrays(), view.antialiased, out, valid, visible)  # fmt: skip
        view.valid = valid
        ctx.view = view
        ctx.dtypes = tuple(t.dtype for t in (means, quats, scales, opacities))
        means2d, conics, opacity, depth, extents = (torch.from_numpy(a) for a in out)
        shown = torch.from_numpy(visible)
        ctx.mark_non_differentiable(extents, shown)
        return means2d, conics, opacity, depth, extents, shown

    @staticmethod
    def backward(  # type: ignore[override]
        ctx: Any, *grads: Tensor | None
    ) -> tuple[Tensor | None, ...]:
        from dyngs.renderers import project_kernels as pk

        view: _View = ctx.view
        n = view.scene.shape[1]
        shapes = [(n, k) if k > 1 else (n,) for k in pk.OUT_COLUMNS[:4]]
        upstream = tuple(
            np.zeros(shape) if grad is None else _numpy(grad.to(GEOMETRY_DTYPE).reshape(shape))
            for grad, shape in zip(grads[:4], shapes, strict=True)
        )
        result = tuple(torch.empty(shape, dtype=dtype) for shape, dtype in
                       zip(((n, 3), (n, 4), (n, 3), (n,)), ctx.dtypes, strict=True))  # fmt: skip
        signature = "/".join(str(d)[6:] for d in ctx.dtypes)
        run_kernel(pk.project_backward, view.threads, signature, view.scene, view.finite,
                   view.arrays(), view.valid, view.antialiased, upstream,
                   tuple(t.numpy() for t in result))  # fmt: skip
        return (*result, None)


def bin_tiles_compiled(
    screen: ScreenGaussians, width: int, height: int, tile_size: int
) -> TileBins:
    """`stages.bin_tiles` in one compiled pass (`tile_kernels.bin_by_depth`): the depth
    order by a stable radix sort, each Gaussian's pixel box, and a counting sort of the
    pairs into tiles (O(M), where the reference expands and sorts them in PyTorch). The
    same bins, element for element (tests/renderers/test_cpu_tile.py)."""
    from dyngs.renderers import tile_kernels

    layout = (-(-width // tile_size), tile_size, width, height)
    geometry = (t.to(GEOMETRY_DTYPE) for t in (screen.depths, screen.means2d, screen.extents))
    depths, means2d, extents = (_numpy(t) for t in geometry)
    gaussian, start, count = tile_kernels.bin_by_depth(
        depths, _numpy(screen.visible), means2d, extents, layout
    )
    return TileBins(
        gaussian=torch.from_numpy(gaussian),
        tile_start=torch.from_numpy(start),
        tile_count=torch.from_numpy(count),
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
        deal = plan.deal()
        sums = np.zeros((height, width, 5), dtype=scene[3].dtype)
        state = (height, width) if plan.backward else (0, 0)
        transmittance = np.ones(state)
        last = np.full(state, -1, dtype=np.int64)
        alphas = _ALPHAS.take(plan, deal, scene[3].dtype)
        feet = np.empty((len(scene[4]) if plan.backward else 0, 5), dtype=np.int64)
        kept = (transmittance, last, alphas, feet)
        per_pair = np.zeros(len(scene[4]) if plan.contribution else 0)
        plan.work = np.zeros((len(deal[0]), 2), dtype=np.int64)
        _launch(tile_kernels.composite_forward, plan.threads, scene, deal, plan.layout(),
                plan.limits(), sums, kept, per_pair, plan.work)  # fmt: skip
        ctx.plan = plan
        ctx.state = (scene, deal, kept)
        if plan.backward:  # back to the store when the graph (and with it ctx) is freed
            weakref.finalize(ctx, _ALPHAS.give, alphas)
        contribution = torch.from_numpy(per_pair)
        ctx.mark_non_differentiable(contribution)
        return torch.from_numpy(sums), contribution

    @staticmethod
    def backward(  # type: ignore[override]
        ctx: Any, grad_sums: Tensor, _grad_contribution: Tensor | None
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, None]:
        from dyngs.renderers import tile_kernels

        plan: _Plan = ctx.plan
        scene, deal, kept = ctx.state
        pair_grads = np.empty((len(scene[4]), tile_kernels.PAIR_GRADS))
        upstream = _numpy(grad_sums)  # the kernel widens it to float64 as it reads it
        _launch(tile_kernels.composite_backward, plan.threads, scene, deal, plan.layout(),
                plan.limits(), upstream, kept, pair_grads)  # fmt: skip
        grads = torch.from_numpy(_per_gaussian(plan.bins, pair_grads, len(scene[0])))
        if plan.absgrad is not None:
            plan.absgrad.copy_(grads[:, 10:12])
        feature_dtype = torch.from_numpy(scene[3][:0]).dtype
        return (
            grads[:, 0:2],
            grads[:, 2:5],
            grads[:, 5],
            grads[:, 6:10].to(feature_dtype),
            None,
        )

"""Adaptive density control of 3D Gaussian Splatting (Kerbl et al. 2023): clone small and
split large Gaussians whose screen-space gradient is high, prune transparent or oversized
ones, and periodically reset opacities.

State is explicit (`DensifyState`), and every change of the Gaussian set is described by
a `TopologyChange` that each owner of per-Gaussian data applies (parameters, optimizer
moments, flags, neighbour lists).

Letters: N Gaussians before a change, M after.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from dyngs.engine.optim import replace_rows
from dyngs.errors import ConfigError
from dyngs.geometry import normalize_quaternion, quaternion_to_rotation
from dyngs.model import GAUSSIAN_PARAMS, DynamicGaussians
from dyngs.renderers.base import RenderOutput


@dataclass(frozen=True)
class DensifyConfig:
    """When and how Gaussians are cloned, split and pruned."""

    grad_threshold: float = 2e-4
    """Densify Gaussians whose mean screen-space gradient (NDC units) exceeds this (3DGS)."""
    absgrad: bool = True
    """Densify by the absolute gradient, Σ over pixels of |∂L/∂means2d| (AbsGS, Ye et al.
    2024), against `absgrad_threshold`, rather than by the gradient against
    `grad_threshold`. Where a Gaussian blurs detail, per-pixel gradients of both signs
    cancel in the gradient but not here, so it still asks to be split. On our scenes it
    draws about as well with markedly fewer Gaussians, so a time budget buys more steps
    (docs/ACCURACY.md).
    `--densify.no-absgrad` is 3DGS's rule; renderers that cannot measure it fall back."""
    absgrad_threshold: float = 8e-4
    """The threshold on the mean absolute gradient (NDC units; AbsGS and gsplat use 4× the
    gradient's, as the absolute sum is larger)."""
    refine_every: int = 100
    """Iterations between densification steps."""
    refine_start: int = 300
    """First iteration that densifies (3DGS: 500 of 30k; our runs are shorter)."""
    refine_stop: float = 0.5
    """Stop densifying after this fraction of the run (3DGS: 15k of 30k)."""
    reset_opacity_every: int = 3000
    """Clamp every opacity to `reset_opacity` this often while densifying (0: never)."""
    reset_opacity: float = 0.01
    pause_after_reset: int = 0
    """Refinements skipped for this many steps after each opacity reset, so that clones,
    splits and prunes are judged on opacities that have grown back rather than on the
    errors the reset itself made (gsplat's `pause_refine_after_reset`, which suggests
    the number of training images). 0: refine on schedule."""
    percent_dense: float = 0.01
    """Gaussians larger than this fraction of the scene extent are split, smaller cloned."""
    split_children: int = 2
    split_shrink: float = 1.6
    """Children of a split are this much smaller (3DGS: 0.8 × number of children)."""
    prune_opacity: float = 0.005
    """Prune Gaussians more transparent than this at every time of the sequence (opacity
    × the largest temporal factor over t ∈ [0, 1]): a temporal Gaussian whose lifetime
    has drifted past either end draws nothing, and no view's gradient brings it back."""
    prune_world_size: float = 0.1
    """After the first opacity reset, prune Gaussians larger than this fraction of the extent."""
    prune_screen_size: float = 0.0
    """After the first opacity reset, also prune Gaussians whose radius on screen exceeded
    this many pixels since the last refinement; 0 (the default) never does. 3DGS (Kerbl et
    al. 2023) describes 20 px, but its code zeroed the radii before reading them, so the
    published results never pruned so (its authors, graphdeco-inria/gaussian-splatting
    issues #123 and #643), and gsplat leaves it off. Applied, it pruned a real capture's
    background (large on screen by nature) at every refinement after the reset, and each
    view drew nearly black until the next regrowth (docs/TRAINING.md)."""
    prune_importance: float = 0.5
    """Prune Gaussians that were seen but never made more than this many pixels' worth of
    any view (blending weight summed over its pixels): even wholly wrong, such a Gaussian
    moves a view's L1 by under half a pixel, so it buys nothing for its cost (the
    accumulated-weight importance of LightGaussian, Fan et al. 2023). 0 switches it off."""
    importance_views: int = 100
    """Before each refinement, render this many training views of the time window (all of
    them when fewer; spread evenly over time), without gradient, and prune by the largest
    share each Gaussian makes of any of them. 0: only the views drawn since the last
    refinement count, which miss some of the window's views (docs/CAPACITY.md)."""
    importance_factor: int = 2
    """Those views are rendered at 1/this of their size where they keep `--coarse.min-side`
    pixels on their shorter side (the small scenes never shrink), and each Gaussian's share
    is counted in whole-view pixels: the same sum of blending weights, estimated on a
    quarter of the pixels. On a real capture the whole views made the pass a large share
    of a budgeted run's time (docs/CAPACITY.md). 1: whole."""
    grow_min_life: float | None = None
    """Gaussians whose temporal opacity lives shorter than this (its σ, in units of the
    sequence) are neither cloned nor split. Such a Gaussian draws a few frames, and so
    would its copies: they fit those training frames, and between them, where held-out
    times lie, they fade out and in. Left to grow, they drew mujoco-scale_change's late
    times in some seeds, with holes and wisps, where in the others the deformation
    carried long-lived Gaussians there (docs/ACCURACY.md, "Short-lived Gaussians do not
    grow"). None: one time cell of the data-sized field (`time_cells`: six
    timestamps' span when one view sees each time, two from three views on); 0: every
    Gaussian may grow."""
    max_gaussians: int | None = None
    """The Gaussian budget: densification never goes beyond it (highest gradients first). The
    cap grows linearly toward it over the densification window. None: sized from the data
    (dyngs/engine/capacity.py)."""

    def __post_init__(self) -> None:
        if self.importance_views < 0:
            raise ConfigError(
                f"--densify.importance-views must be ≥ 0, got {self.importance_views}"
            )
        if self.importance_factor < 1:
            raise ConfigError(
                f"--densify.importance-factor must be ≥ 1, got {self.importance_factor}"
            )
        if self.pause_after_reset < 0:
            raise ConfigError(
                f"--densify.pause-after-reset must be ≥ 0, got {self.pause_after_reset}"
            )
        if self.grow_min_life is not None and not self.grow_min_life >= 0.0:  # NaN fails
            raise ConfigError(f"--densify.grow-min-life must be ≥ 0, got {self.grow_min_life}")


@dataclass
class TopologyChange:
    """Row i of the new set came from row source[i] of the old one; `fresh` rows are new
    Gaussians (clones, split children) rather than survivors."""

    source: Int[Tensor, " M"]
    fresh: Bool[Tensor, " M"]


@dataclass
class DensifyState:
    """Per-Gaussian statistics gathered between two refinements."""

    grad_sum: Float[Tensor, " N"]
    count: Float[Tensor, " N"]
    max_radius: Float[Tensor, " N"]
    importance: Float[Tensor, " N"]
    """Largest share of one view's picture (blending weight summed over pixels) it made."""
    pull: Float[Tensor, "N 3"]
    """Σ ∂L/∂μ · (t - ½): the loss gradient with respect to a velocity the Gaussian does not
    have (μ(t) = μ + v (t - ½)); large when it is pulled one way early and another late."""
    pull_norm: Float[Tensor, " N"]
    """Σ |∂L/∂μ · (t - ½)|, so that |pull| / pull_norm ∈ [0, 1] measures how consistently."""
    sh_pull: Float[Tensor, "N 7 3"]
    """Σ over views of the gradient of the first SH band not in use (frozen at zero; up to
    7 coefficients per channel)."""
    sh_pull_norm: Float[Tensor, " N"]
    """Σ over views of that gradient's norm."""

    @staticmethod
    def zeros(n: int, device: torch.device) -> DensifyState:
        def zeros(*shape: int) -> Tensor:
            return torch.zeros(n, *shape, device=device)

        return DensifyState(
            zeros(), zeros(), zeros(), zeros(), zeros(3), zeros(), zeros(7, 3), zeros()
        )

    def state_dict(self) -> dict[str, Tensor]:
        return {name: getattr(self, name) for name in _STATE_NAMES}

    @staticmethod
    def from_state_dict(d: dict[str, Tensor]) -> DensifyState:
        # Checkpoints from before these were measured: start them afresh.
        fresh = DensifyState.zeros(len(d["count"]), d["count"].device)
        fresh.importance.fill_(math.inf)
        for name in _STATE_NAMES:
            if name in d:
                setattr(fresh, name, d[name])
        return fresh

    def pull_coherence(self) -> Float[Tensor, " N"]:
        return self.pull.norm(dim=-1) / self.pull_norm.clamp_min(1e-30)

    def sh_coherence(self) -> float:
        """How consistently, over all Gaussians, the frozen band's gradient points one way."""
        total = float(self.sh_pull_norm.sum())
        return float(self.sh_pull.flatten(1).norm(dim=-1).sum()) / total if total > 0 else 0.0


_STATE_NAMES = (
    "grad_sum",
    "count",
    "max_radius",
    "importance",
    "pull",
    "pull_norm",
    "sh_pull",
    "sh_pull_norm",
)


def band_rows(degree: int) -> slice:
    """Rows of band `degree` (≥ 1) in the SH coefficients without the DC term."""
    return slice(degree * degree - 1, (degree + 1) * (degree + 1) - 1)


def probe_band(state: DensifyState, sh_rest: Tensor, degree: int) -> None:
    """Gather the gradient of band `degree`, which is rendered at zero but must not learn
    yet, and clear it so that the optimizer leaves the band at zero."""
    grad = sh_rest.grad
    if grad is None:
        return
    with torch.no_grad():
        rows = band_rows(degree)
        band = grad[:, rows]
        state.sh_pull[:, : band.shape[1]] += band.to(state.sh_pull.dtype)
        state.sh_pull_norm += band.flatten(1).norm(dim=-1).to(state.sh_pull_norm.dtype)
        grad[:, rows] = 0


@dataclass
class StepStatistics:
    """What the views of one step add to a `DensifyState`: sums (a process's share, summed
    over the processes before use) and maxima (their largest)."""

    grad_sum: Float[Tensor, " N"]
    count: Float[Tensor, " N"]
    pull: Float[Tensor, "N 3"]
    pull_norm: Float[Tensor, " N"]
    max_radius: Float[Tensor, " N"]
    importance: Float[Tensor, " N"]
    """+inf where a view did not measure it (never prune by what was not measured)."""

    def sums(self) -> list[Tensor]:
        return [self.grad_sum, self.count, self.pull, self.pull_norm]

    def maxima(self) -> list[Tensor]:
        return [self.max_radius, self.importance]

    @staticmethod
    def zeros(n: int, device: torch.device) -> StepStatistics:
        """Nothing seen: the identity of `combine` (every statistic is ≥ 0)."""
        z = torch.zeros(n, device=device)
        return StepStatistics(z, z.clone(), torch.zeros(n, 3, device=device), z.clone(),
                              z.clone(), z.clone())  # fmt: skip

    def combine(self, other: StepStatistics) -> StepStatistics:
        """Both views' statistics: sums added, maxima kept."""
        summed = [a + b for a, b in zip(self.sums(), other.sums(), strict=True)]
        largest = [torch.maximum(a, b) for a, b in zip(self.maxima(), other.maxima(), strict=True)]
        return StepStatistics(*summed, *largest)


def view_statistics(
    out: RenderOutput,
    width: int,
    height: int,
    means_grad: Tensor | None = None,
    time: float = 0.5,
    views: int = 1,
    absgrad: bool = False,
    pixel_scale: float = 1.0,
) -> StepStatistics | None:
    """One view's screen-space gradients, and the canonical means' gradient at its time
    (call after backward; None when nothing reached the screen). With the loss averaged
    over `views` views, gradients are scaled back to one view's, as gsplat does for
    batches, so that `--densify.grad-threshold` keeps its meaning. Radii are counted in
    pixels `pixel_scale` times smaller than the render's (the view's own pixels, for a
    coarse render), so that `--densify.prune-screen-size` keeps its meaning too."""
    grad = out.means2d.grad
    if grad is None:
        return None
    if absgrad and out.means2d_absgrad is not None:
        grad = out.means2d_absgrad
    with torch.no_grad():
        # 3DGS thresholds gradients of NDC coordinates; ours are per pixel.
        scale = grad.new_tensor([0.5 * width * views, 0.5 * height * views])
        norm = (grad * scale).norm(dim=-1).to(torch.get_default_dtype())
        seen = out.visible
        zeros = torch.zeros_like(norm)
        radius = out.radii.max(dim=-1).values.to(norm.dtype)
        if pixel_scale != 1.0:
            radius = radius * pixel_scale
        if out.contribution is None:
            # Not measured (not asked for, or the renderer cannot): never prune by it. When
            # the window's views decide, `measure_importance` replaces it before refining.
            importance = torch.full_like(norm, math.inf)
        else:
            importance = out.contribution.to(norm.dtype)
        pull = torch.zeros(len(norm), 3, dtype=norm.dtype, device=norm.device)
        pull_norm = zeros
        if means_grad is not None:
            pull = means_grad.to(norm.dtype) * (time - 0.5)
            pull_norm = pull.norm(dim=-1)
        return StepStatistics(torch.where(seen, norm, 0), seen.to(norm.dtype), pull, pull_norm,
                              torch.where(seen, radius, 0), importance)  # fmt: skip


def add_statistics(state: DensifyState, stats: StepStatistics) -> None:
    """Add a step's (all processes') statistics to the state."""
    with torch.no_grad():
        state.grad_sum += stats.grad_sum.to(state.grad_sum.dtype)
        state.count += stats.count.to(state.count.dtype)
        state.max_radius.copy_(torch.maximum(state.max_radius, stats.max_radius))
        state.importance.copy_(torch.maximum(state.importance, stats.importance))
        state.pull += stats.pull.to(state.pull.dtype)
        state.pull_norm += stats.pull_norm.to(state.pull_norm.dtype)


def accumulate(
    state: DensifyState,
    out: RenderOutput,
    width: int,
    height: int,
    means_grad: Tensor | None = None,
    time: float = 0.5,
) -> None:
    """Add one view's screen-space gradients, and the canonical means' gradient at its
    time (call after backward)."""
    stats = view_statistics(out, width, height, means_grad, time)
    if stats is not None:
        add_statistics(state, stats)


def plan_refinement(
    config: DensifyConfig,
    model: DynamicGaussians,
    state: DensifyState,
    step: int,
    extent: float,
    generator: torch.Generator | None = None,
    budget: int | None = None,
) -> tuple[TopologyChange, dict[str, Tensor]] | None:
    """Decide clones, splits and prunes; returns the change and the new raw parameters.
    Growth stops at `budget` Gaussians (`schedules.budget_at`; None: no cap)."""
    c = model.canonical
    with torch.no_grad():
        n = len(c)
        avg = state.grad_sum / state.count.clamp_min(1)
        scale_max = c.log_scales.exp().max(dim=-1).values
        prune = torch.sigmoid(c.opacity_logits) * c.peak_presence() < config.prune_opacity
        prune |= (state.count > 0) & (state.importance < config.prune_importance)
        if config.reset_opacity_every > 0 and step > config.reset_opacity_every:
            prune |= scale_max > config.prune_world_size * extent
            if config.prune_screen_size > 0:
                prune |= state.max_radius > config.prune_screen_size
        prune |= ~c.finite_rows()
        threshold = config.absgrad_threshold if config.absgrad else config.grad_threshold
        grow = (avg >= threshold) & ~prune
        if config.grow_min_life:  # None (not yet sized) and 0 let every Gaussian grow
            grow &= c.time_log_scales >= math.log(config.grow_min_life)
        # Respect the budget: each clone adds one, each split adds children - 1.
        room = (2**62 if budget is None else budget) - (n - int(prune.sum()))
        if room <= 0:
            grow[:] = False
        elif int(grow.sum()) > room // max(config.split_children - 1, 1):
            keep = room // max(config.split_children - 1, 1)
            top = torch.topk(torch.where(grow, avg, -1.0), keep).indices
            grow[:] = False
            grow[top] = True
        small = scale_max <= config.percent_dense * extent
        clone, split = grow & small, grow & ~small
        if not (bool(prune.any()) or bool(clone.any()) or bool(split.any())):
            return None

        survivors = (~prune & ~split).nonzero().squeeze(1)
        cloned = clone.nonzero().squeeze(1)
        parents = split.nonzero().squeeze(1).repeat(config.split_children)
        source = torch.cat((survivors, cloned, parents))
        fresh = torch.zeros(len(source), dtype=torch.bool, device=source.device)
        fresh[len(survivors) :] = True

        values = {name: getattr(c, name).detach()[source].clone() for name in GAUSSIAN_PARAMS}
        if len(parents):
            # Children are drawn from the parent Gaussian and shrunk (3DGS).
            children = slice(len(survivors) + len(cloned), len(source))
            scales = c.log_scales.detach()[parents].exp()
            rot = quaternion_to_rotation(normalize_quaternion(c.quats.detach()[parents]))
            offset = torch.randn(scales.shape, generator=generator, device=scales.device) * scales
            values["means"][children] += (rot @ offset[..., None]).squeeze(-1)
            values["log_scales"][children] = (scales / config.split_shrink).log()
    return TopologyChange(source, fresh), values


def apply_topology(
    model: DynamicGaussians,
    optimizer: torch.optim.Optimizer,
    change: TopologyChange,
    values: dict[str, Tensor],
) -> None:
    """Make every owner of per-Gaussian data follow `change`: the parameters (replaced by
    `values`), Adam's moments (rows moved, fresh rows zeroed) and the model's flags."""
    old = model.canonical.params()
    model.canonical.replace(values)
    new = model.canonical.params()
    for name in GAUSSIAN_PARAMS:
        replace_rows(optimizer, old[name], new[name], change.source, change.fresh)
    model.on_topology(change.source, change.fresh)


def reset_opacity_logits(logits: Tensor, ceiling: float) -> Tensor:
    """Opacity logits clamped so that no opacity exceeds `ceiling` (3DGS opacity reset)."""
    return logits.clamp_max(math.log(ceiling / (1 - ceiling)))

"""When things happen in a run: pure functions of the config and the step.

A run of `max_iters` steps is laid out as:

    step 0 ── warm-up ──► warmup_iters ── time window widens ──► window full ── … ──► end
              static,                    frontier draws,          motion revisits
              t ≤ warmup_time            refinement (densify/prune) until refine_stop

Nothing here reads or changes state: the trainer and the lifecycle ask these functions
what a step is, and tests can check a schedule without training anything.

What is laid out in fractions of the run (the time window, densification, the
learning-rate decay) is read at the step's `position` on a schedule of `length` steps:
the step itself on a schedule of `max_iters`, unless `--time-budget` re-planned the step
count (`TrainConfig.pace`). Periodic events (every `refine_every` steps, …) count steps.
"""

from __future__ import annotations

import dataclasses
import math

from dyngs.config import CoarseConfig, TrainConfig
from dyngs.datamanagers.images import downscaled_size
from dyngs.engine.optim import deformation_rate_scale
from dyngs.types import Camera


def length(config: TrainConfig) -> int:
    """Steps the schedule is laid out for: `max_iters`, or the length it had when a time
    budget first re-planned the run."""
    return config.steps if config.pace is None else config.pace[2]


def position(config: TrainConfig, step: int) -> float:
    """Where `step` falls on the schedule of `length` steps: the step itself, or after a
    re-plan at step a (position p there) the rest of the schedule spread evenly over the
    steps left, p + (step − a)(length − p)/(max_iters − a), so that the run's last step
    is the schedule's end, whatever the budget chose, and nothing moves back."""
    if config.pace is None:
        return step
    start, at, total = config.pace
    return at + (step - start) * (total - at) / max(config.steps - start, 1)


def repaced(config: TrainConfig, step: int, steps: int) -> TrainConfig:
    """`config` re-planned at `step` to end after `steps` steps: its schedule goes on
    from where it is at `step`, at the pace the new count gives."""
    pace = (step, float(position(config, step)), length(config))
    return dataclasses.replace(config, max_iters=steps, pace=pace)


def deforming(config: TrainConfig, step: int) -> bool:
    """Whether the deformation field is on: after the static warm-up."""
    return step >= config.warmup_iters


def time_window(config: TrainConfig, step: int) -> float:
    """Latest time trained on at `step`: `warmup_time` through the warm-up, then widening
    linearly to 1 over `time_ramp` of the run."""
    if step < config.warmup_iters:
        return config.warmup_time
    ramp = config.time_ramp * length(config)
    if ramp <= 0:
        return 1.0
    widened = (1 - config.warmup_time) * (position(config, step) - config.warmup_iters) / ramp
    return min(1.0, config.warmup_time + widened)


def time_jitter(config: TrainConfig, step: int) -> float:
    """Standard deviation of the training views' time noise at `step`, in units of the
    training times' spacing: `time_jitter`, decaying linearly to 0 at the schedule's end
    (Yang et al. 2024 decay theirs over a fixed 20 000 steps, longer than most runs here)."""
    return config.time_jitter * max(0.0, 1.0 - position(config, step) / max(length(config), 1))


def window_full_step(config: TrainConfig) -> float:
    """Position (`position`) at which the time window spans the whole sequence."""
    return config.warmup_iters + config.time_ramp * length(config)


def is_frontier_step(config: TrainConfig, step: int) -> bool:
    """Whether this step trains on the newest part of a widening window: `frontier_share`
    of the steps, spread evenly (step s is one when ⌊(s + 1)·share⌋ > ⌊s·share⌋)."""
    share = config.frontier_share
    return (
        deforming(config, step)
        and time_window(config, step) < 1.0
        and math.floor((step + 1) * share) > math.floor(step * share)
    )


def learning_progress(config: TrainConfig, step: int) -> tuple[float, float | None, float]:
    """`set_learning_rates`' arguments at `step`: how far the learning rates have decayed
    (the run's progress, and the deformation's from the step the time window is full when
    `--optim.hold-deformation-rates`), and the share of its rates the deformation learns
    at over the steps now planned (`deformation_rate_scale`)."""
    at, total = position(config, step), length(config)
    progress = at / max(total, 1)
    scale = deformation_rate_scale(config.optim, config.steps)
    if not config.optim.hold_deformation_rates:
        return progress, None, scale
    full = window_full_step(config)
    return progress, (at - full) / max(total - full, 1), scale


def coarse_factor(config: TrainConfig, step: int, camera: Camera) -> int:
    """The factor a training view from `camera` is shrunk by at `step`: `--coarse.factor`
    while the schedule is within `--coarse.until` of the run and the shrunk view keeps
    `--coarse.min-side` pixels on its shorter side, else 1 (drawn whole)."""
    c = config.coarse
    if position(config, step) >= c.until * length(config):
        return 1
    return _shrink_factor(camera, c.factor, c.min_side)


def importance_factor(config: TrainConfig, camera: Camera) -> int:
    """The factor an importance view (`--densify.importance-views`) from `camera` is
    rendered shrunk by: `--densify.importance-factor` where the shrunk view keeps
    `--coarse.min-side` pixels on its shorter side, as a coarse view must, else 1."""
    return _shrink_factor(camera, config.densify.importance_factor, config.coarse.min_side)


def _shrink_factor(camera: Camera, factor: int, min_side: int) -> int:
    """`factor` if a view from `camera` shrunk by it keeps `min_side` pixels on its shorter
    side, else 1."""
    if factor == 1:
        return 1
    size = downscaled_size(camera.width, camera.height, factor)
    return factor if min(size) >= min_side else 1


def refine_stop(config: TrainConfig) -> float:
    """Last position (`position`) that may densify or prune."""
    return config.densify.refine_stop * length(config)


def is_refine_step(config: TrainConfig, step: int) -> bool:
    """Whether Gaussians are cloned, split and pruned after `step` steps."""
    d = config.densify
    within = d.refine_start <= position(config, step) <= refine_stop(config)
    return within and step % d.refine_every == 0 and step > 0 and not _paused(config, step)


def _paused(config: TrainConfig, step: int) -> bool:
    """Whether `step` falls within `--densify.pause-after-reset` steps after a reset (the
    refinement at a reset step itself comes before its reset, and is not paused)."""
    every, pause = config.densify.reset_opacity_every, config.densify.pause_after_reset
    if every <= 0 or pause <= 0:
        return False
    last = step // every * every
    return 0 < step - last <= pause and is_reset_step(config, last)


def is_filter_step(config: TrainConfig, step: int) -> bool:
    """Whether the 3D filter is refreshed after `step` steps: every `refine_every` steps,
    but not within the last `refine_every`, so that the run ends trained on the filter it
    keeps (Mip-Splatting's schedule, Yu et al. 2024). It is also set before step 0."""
    every = config.densify.refine_every
    return (
        config.gaussians.filter_3d > 0
        and step > 0
        and step % every == 0
        and step <= config.steps - every
    )


def budget_at(config: TrainConfig, step: int) -> int:
    """The Gaussian cap at `step`: a quarter of the budget when densification starts, growing
    linearly to all of it by the end of the densification window."""
    d = config.densify
    if d.max_gaussians is None:
        return 2**62
    at = position(config, step)
    progress = (at - d.refine_start) / max(refine_stop(config) - d.refine_start, 1)
    return int(d.max_gaussians * (0.25 + 0.75 * min(max(progress, 0.0), 1.0)))


def is_reset_step(config: TrainConfig, step: int) -> bool:
    """Whether every opacity is clamped down after `step` steps (3DGS's opacity reset)."""
    every = config.densify.reset_opacity_every
    periodic = every > 0 and step > 0 and step % every == 0
    return periodic and position(config, step) <= refine_stop(config)


def is_motion_step(config: TrainConfig, step: int) -> bool:
    """Revisit the static/dynamic split every `motion.every` steps once training spans
    all times."""
    return (
        config.motion.separate
        and deforming(config, step)
        and time_window(config, step) >= 1.0
        and step % config.motion.every == 0
    )


def is_pixel_start(config: TrainConfig, step: int) -> bool:
    """Whether the split is started from fixed cameras' pixels after `step` steps: at the
    end of the warm-up, when `--motion.start-from-pixels`."""
    m = config.motion
    return m.separate and m.start_from_pixels and step == config.warmup_iters > 0


def is_promotion_step(config: TrainConfig, step: int) -> bool:
    """Whether static Gaussians that move are promoted after `step` steps: every
    `motion.every` steps while the window widens, after a split started from pixels."""
    m = config.motion
    return (
        m.separate
        and m.start_from_pixels
        and step > config.warmup_iters > 0
        and time_window(config, step) < 1.0
        and step % m.every == 0
    )


def probe_degree(config: TrainConfig, active: int) -> int | None:
    """The SH band rendered frozen at zero to gather evidence for it, if any."""
    g = config.gaussians
    if g.sh_evidence > 0 and active < g.sh_degree:
        return active + 1
    return None


def is_sh_step(config: TrainConfig, step: int, active: int) -> bool:
    """Whether the SH degree may rise after `step` steps: every `sh_degree_interval` steps
    while below the highest degree (3DGS's schedule). It then rises at once when
    `sh_evidence` is 0, else only when the evidence asks for it (`sh_evidence_needed`)."""
    g = config.gaussians
    return active < g.sh_degree and step % max(g.sh_degree_interval, 1) == 0


def chance_coherence(views: int) -> float:
    """Chance alone makes a gradient summed over `views` views about 1/√views consistent;
    evidence must clear three times that."""
    return 3 / math.sqrt(max(views, 1))


def sh_evidence_needed(config: TrainConfig, views: int) -> float:
    """How consistent the frozen band's gradient must be for the SH degree to rise."""
    return max(config.gaussians.sh_evidence, chance_coherence(views))


def schedule_warning(config: TrainConfig) -> str | None:
    """A one-line warning when the run is too short for densification to happen."""
    d = config.densify
    if config.steps > 0 and d.refine_start > refine_stop(config):
        return (
            f"warning: no densification in this run: it would start at step "
            f"{d.refine_start} and stop at {d.refine_stop:g} × {config.steps} = "
            f"{refine_stop(config):g} (lower --densify.refine-start)"
        )
    return None


def coarse_note(config: TrainConfig, cameras: list[Camera]) -> str | None:
    """What `--coarse` does to the training views from `cameras`: how many are drawn
    coarse; that none is, when the flags asked for something other than the default."""
    c = config.coarse
    if c.until == 0:
        return None
    coarse = sum(coarse_factor(config, 0, camera) > 1 for camera in cameras)
    if coarse == 0:
        if c == CoarseConfig():  # the default on a small scene: it trains as it did
            return None
        return (
            f"[coarse] every training view is drawn whole: none keeps {c.min_side} px "
            f"on its shorter side at 1/{c.factor} of its size (--coarse.min-side)"
        )
    return (
        f"[coarse] {coarse} of {len(cameras)} training views are drawn at 1/{c.factor} of "
        f"their size for the first {c.until:.0%} of the run, whole after it"
    )


def plan_notes(config: TrainConfig, sized: str | None) -> list[str | None]:
    """What a run says of its plan before its first step: a densification window it is too
    short for, a step count sized from the data (`sized` says from what), a time budget."""
    notes = [schedule_warning(config)]
    if sized is not None:
        notes.append(f"[schedule] {config.steps} steps, sized from the data ({sized})")
    scale = deformation_rate_scale(config.optim, config.steps)
    if scale < 1:
        resized = "; each re-plan of the budget sizes it again" if config.time_budget else ""
        notes.append(
            f"[rates] the deformation learns at {scale:.2f}× --optim.grid and --optim.network "
            f"over {config.steps} steps (--optim.deformation-steps){resized}"
        )
    if config.time_budget is not None:
        notes.append(
            f"[budget] {config.time_budget:g} min of training: the {config.steps} planned "
            "steps are re-planned from the measured step rate as the run goes"
        )
    return notes

"""What happens to the model between training steps, and at the end of a run.

After each good step (`after_step`), in this order:
1. **the static/dynamic split** (`MotionSplit`, `dyngs.engine.motion`): with fixed
   cameras it starts from their pixels at the end of the warm-up, and only promotes
   while the time window widens; once it is full, Gaussians that stopped moving become
   static and static ones where something moves become dynamic;
2. **SH degree**: at each interval it may rise by one, when the frozen band's gradient
   asks for it (or on schedule, `--gaussians.sh-evidence 0`);
3. **3D filter**: every `refine_every` steps, each Gaussian's smoothing filter is set
   from the finest sampling rate of the training views that see it
   (Mip-Splatting, `GaussianConfig.filter_3d`; also once when the run starts);
4. **refinement** (`dyngs.engine.densify`): the importance of every Gaussian is measured
   on the time window's views, then Gaussians are cloned, split and pruned within the
   budget, and every owner of per-Gaussian data follows the change;
5. **opacity reset** (3DGS), with Adam's moments of the opacities cleared.

At the end (`finish`): a last motion revisit, then the field is cut to the span of the
dynamic Gaussians. The schedule of all of this is `dyngs.engine.schedules`; the state it
keeps between refinements is `DensifyState`, saved with the checkpoint.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from functools import cached_property

import torch
from rich.console import Console
from torch import Tensor

from dyngs.config import TrainConfig
from dyngs.datamanagers.datamanager import DataManager, TrainBatch
from dyngs.engine import schedules
from dyngs.engine.capacity import data_scale
from dyngs.engine.densify import (
    DensifyState,
    StepStatistics,
    add_statistics,
    apply_topology,
    plan_refinement,
    probe_band,
    reset_opacity_logits,
    view_statistics,
)
from dyngs.engine.distributed import SINGLE, ProcessGroup
from dyngs.engine.motion import FixedCameraMotion, model_bytes, revisit, sample_times
from dyngs.engine.optim import replace_params
from dyngs.engine.smoothing import refresh_filter
from dyngs.engine.writer import Writer
from dyngs.fields.base import Croppable
from dyngs.model import DynamicGaussians
from dyngs.renderers.base import ABSENT_BELOW, ContributionRenderer, Renderer, RenderOutput
from dyngs.types import Camera, Gaussians


class Lifecycle:
    """The model's changes between steps (see the module docstring).

    `extent` (the cameras' radius) scales densification thresholds; `pixel_size` (world
    size of a pixel at the scene centre) is what "moves less than half a pixel" means.
    `on_topology` is called after every change of the Gaussian set, so that other owners
    of per-Gaussian data (the rigidity term's neighbourhoods) follow. The renderer and the
    optimizer stay the trainer's (it rebuilds the optimizer on resume): the methods that
    need them are given them. Under several processes (`group`), every rank holds the same
    statistics (the trainer sums each step's over the ranks) and so makes the same changes;
    the importance renders and the 3D filter's views are shared out and their maxima
    exchanged.
    """

    def __init__(
        self,
        config: TrainConfig,
        model: DynamicGaussians,
        data: DataManager,
        writer: Writer,
        console: Console,
        generator: torch.Generator,
        extent: float,
        pixel_size: float,
        on_topology: Callable[[], None] = lambda: None,
        group: ProcessGroup = SINGLE,
    ) -> None:
        self.config = config
        self.group = group
        self.model = model
        self.data = data
        self.writer = writer
        self.console = console
        self.generator = generator
        self.extent = extent
        self.on_topology = on_topology
        self.device = model.canonical.means.device
        self.state = DensifyState.zeros(len(model.canonical), self.device)
        self.importance_seconds = 0.0
        self.filter_seconds = 0.0
        self.motion = MotionSplit(config, model, data, writer, pixel_size, self._say)
        if config.gaussians.filter_3d > 0:  # as Mip-Splatting sizes its initial Gaussians'
            self.refresh_filter()

    def refresh_filter(self) -> None:
        """Set the 3D filter from every training view (`smoothing.refresh_filter`)."""
        poses = self.group.share(self.data.train_poses())
        strength = self.config.gaussians.filter_3d
        self.filter_seconds += refresh_filter(self.model, poses, strength, self.group)

    # ------------------------------------------------------------ during a step

    def probe_degree(self) -> int | None:
        """The SH degree to draw this step with, when a frozen band gathers evidence."""
        return schedules.probe_degree(self.config, self.model.active_sh_degree)

    def measures_each_step(self, renderer: Renderer) -> bool:
        """Whether every training step must measure its view's contributions: importance
        is the largest share of the views drawn since the last refinement
        (`--densify.importance-views 0`). Otherwise `measure_importance` renders the
        window's views just before each refinement, and no step measures."""
        d = self.config.densify
        return self.prunes_by_importance(renderer) and d.importance_views == 0

    def prunes_by_importance(self, renderer: Renderer) -> bool:
        """Whether refinements prune by importance: asked for, and the renderer can measure
        it (a run whose renderer cannot says so once, when it starts)."""
        asked = self.config.densify.prune_importance > 0
        return asked and isinstance(renderer, ContributionRenderer)

    def importance_note(self, renderer: Renderer) -> str | None:
        """The one-line notice that importance pruning falls back, when it does."""
        if self.config.densify.prune_importance > 0 and not self.prunes_by_importance(renderer):
            return (
                f"[densify] renderer {type(renderer).__name__} cannot measure each "
                "Gaussian's contribution: pruning by opacity and size only"
            )
        return None

    def render(
        self, renderer: Renderer, gaussians: Gaussians, camera: Camera, background: Tensor
    ) -> RenderOutput:
        """A training step's render, in the colours of `camera` (`CameraColours`),
        measuring contributions when pruning reads them each step (`measures_each_step`)."""
        if self.measures_each_step(renderer) and isinstance(renderer, ContributionRenderer):
            out = renderer.with_contribution(gaussians, camera, background)
        else:
            out = renderer(gaussians, camera, background)
        return dataclasses.replace(out, rgb=self.model.camera_colour(out.rgb, camera))

    def gather(self, stats: StepStatistics | None, probe: int | None) -> None:
        """Add a good step's statistics, of every view of every rank (before Adam steps)."""
        if probe is not None:
            probe_band(self.state, self.model.canonical.sh_rest, probe)
        if stats is not None:
            add_statistics(self.state, stats)

    # ------------------------------------------------------------ between steps

    def after_step(self, step: int, optimizer: torch.optim.Optimizer, renderer: Renderer) -> None:
        """Everything due once `step` steps are done (see the module docstring)."""
        cfg = self.config
        self.motion.after_step(step, self.state, optimizer)
        self.consider_sh_degree(step)
        if schedules.is_filter_step(cfg, step):
            self.refresh_filter()
        if schedules.is_refine_step(cfg, step):
            self.refine(step, optimizer, renderer)
        if schedules.is_reset_step(cfg, step):
            logits = self.model.canonical.opacity_logits
            with torch.no_grad():
                logits.copy_(reset_opacity_logits(logits, cfg.densify.reset_opacity))
            for moment in optimizer.state.get(logits, {}).values():
                if isinstance(moment, Tensor) and moment.ndim > 0:
                    moment.zero_()

    def consider_sh_degree(self, step: int) -> None:
        """At each SH interval, raise the degree if the frozen band's evidence asks for it."""
        cfg, model = self.config, self.model
        if not schedules.is_sh_step(cfg, step, model.active_sh_degree):
            return
        if cfg.gaussians.sh_evidence <= 0:
            model.active_sh_degree += 1
            return
        evidence = self.state.sh_coherence()
        self.writer.scalar("sh/evidence", evidence, step)
        if evidence >= schedules.sh_evidence_needed(cfg, self.data.num_train):
            model.active_sh_degree += 1
            self._say(
                f"[sh] view-dependent error (evidence {evidence:.2f}): "
                f"SH degree {model.active_sh_degree}"
            )

    def refine(self, step: int, optimizer: torch.optim.Optimizer, renderer: Renderer) -> None:
        """Measure importance, then clone, split and prune (3DGS adaptive density control)."""
        cfg = self.config
        if self.prunes_by_importance(renderer) and cfg.densify.importance_views > 0:
            started = time.perf_counter()
            self.state.importance = self.measure_importance(step, renderer)
            self.importance_seconds += time.perf_counter() - started
        plan = plan_refinement(
            cfg.densify,
            self.model,
            self.state,
            step,
            self.extent,
            self.generator,
            schedules.budget_at(cfg, step),
        )
        if plan is not None:
            apply_topology(self.model, optimizer, *plan)
            self.on_topology()
        self.state = DensifyState.zeros(len(self.model.canonical), self.device)

    def measure_importance(self, step: int, renderer: Renderer) -> Tensor:
        """Each Gaussian's largest share (blending weight summed over pixels) of any of
        `--densify.importance-views` training views of the time window at `step`, rendered
        now without gradient. The views drawn since the last refinement would be both a
        sample (a Gaussian only undrawn views need looks unimportant) and stale (a view
        drawn long ago vouches for a Gaussian that has since faded); docs/CAPACITY.md."""
        cfg = self.config
        importance = torch.zeros(len(self.model.canonical), device=self.device)
        if not isinstance(renderer, ContributionRenderer):
            return importance.fill_(math.inf)  # never prune by what cannot be measured
        window = schedules.time_window(cfg, step)
        poses = self.data.train_poses(window, cfg.densify.importance_views)
        mine = self.group.share(poses)  # every pose, with one process
        shrink = [(schedules.importance_factor(cfg, camera), camera, t) for camera, t in mine]
        largest_shares(self.model, renderer, shrink, self.data.background, importance)
        self.group.max_([importance])
        return importance

    # ------------------------------------------------------------ static / dynamic

    def read_every_image(self) -> None:
        """Read now what needs every training image (fixed cameras' motion): see `Trainer`."""
        if self.config.motion.separate:
            _ = self.motion.fixed_motion

    def revisit_motion(self, step: int, final: bool = False, demote: bool = True) -> None:
        """Revisit the static/dynamic split with the statistics gathered since the last
        refinement (`MotionSplit.revisit`)."""
        self.motion.revisit(step, self.state, final, demote)

    # ------------------------------------------------------------ the end

    def finish(self, step: int, optimizer: torch.optim.Optimizer) -> None:
        """A last motion revisit (measured motion alone), then the field crop."""
        if self.config.motion.separate and schedules.deforming(self.config, step):
            self.revisit_motion(step, final=True)
        if self.config.motion.crop_field and (said := crop_field(self.model, optimizer)):
            self._say(said)

    # ------------------------------------------------------------ checkpoints

    def seconds(self) -> dict[str, float]:
        """Time spent in the passes over every training view: importance, 3D filter."""
        return {
            "importance_seconds": self.importance_seconds,
            "filter_seconds": self.filter_seconds,
        }

    def state_dict(self) -> dict[str, object]:
        return {"densify": self.state.state_dict(), **self.seconds()}

    def load_state_dict(self, state: dict[str, object]) -> None:
        densify = state["densify"]
        assert isinstance(densify, dict)
        self.state = DensifyState.from_state_dict(densify)
        self.importance_seconds = float(state.get("importance_seconds", 0.0))  # type: ignore[arg-type]
        self.filter_seconds = float(state.get("filter_seconds", 0.0))  # type: ignore[arg-type]

    def _say(self, line: str) -> None:
        self.console.print(line, highlight=False, markup=False)


class MotionSplit:
    """The static/dynamic split between steps (`dyngs.engine.motion`): with fixed cameras,
    started from their pixels at the end of the warm-up and only promoted while the time
    window widens; revisited every `--motion.every` steps once it is full, and a last time
    at the end (measured motion alone)."""

    def __init__(
        self,
        config: TrainConfig,
        model: DynamicGaussians,
        data: DataManager,
        writer: Writer,
        pixel_size: float,
        say: Callable[[str], None],
    ) -> None:
        self.config = config
        self.model = model
        self.data = data
        self.writer = writer
        self.pixel_size = pixel_size
        self.say = say
        self.times = sample_times(data.scene.train.times, config.motion.samples)

    @cached_property
    def fixed_motion(self) -> FixedCameraMotion | None:
        """What the fixed cameras see move (None without any); computed once."""
        fixed = self.data.fixed_cameras
        return None if fixed is None else FixedCameraMotion.of(self.data.scene.train, fixed=fixed)

    def after_step(self, step: int, state: DensifyState, optimizer: torch.optim.Optimizer) -> None:
        """Whatever the split has due once `step` steps are done."""
        cfg, model = self.config, self.model
        if schedules.is_motion_step(cfg, step):
            self.revisit(step, state)
        elif schedules.is_pixel_start(cfg, step) and self.fixed_motion is not None:
            self.start_from_pixels(step, optimizer)
        elif schedules.is_promotion_step(cfg, step) and not bool(model.dynamic.all()):
            self.revisit(step, state, demote=False)

    def start_from_pixels(self, step: int, optimizer: torch.optim.Optimizer) -> None:
        """End of the warm-up: only the Gaussians that most of the fixed cameras that see
        them see change stay dynamic. The field has not been trained yet, so the others
        lose no deformation by turning static, and on a synchronised capture the field is
        cut to the dynamic ones (`--motion.start-crop`). The pixel test reads what each
        Gaussian's pixel shows, so it needs Gaussians on the surfaces: from random points
        or a cloud nobody checked, every Gaussian stays dynamic (from mujoco-collision's
        noise cloud the pixels started 0.1 % dynamic, and the run ended 4.6 dB lower)."""
        assert self.fixed_motion is not None
        model, scene = self.model, self.data.scene
        if not scene.points_on_surfaces:
            self.say(
                f"[motion] fixed cameras, but the initial points ({scene.points_source}) "
                "may not lie on surfaces: every Gaussian stays dynamic until the window is full"
            )
            return
        means = model.canonical.means.detach()
        model.dynamic = self.fixed_motion.evidence(means, self.config.motion)
        share = model.dynamic_fraction()
        self.writer.scalar("motion/dynamic_at_start", share, step)
        self.say(
            f"[motion] fixed cameras: {share:.1%} of the Gaussians sit where pixels change and "
            "start dynamic; the rest start static, promoted when they move"
        )
        trim = self.config.motion.start_crop
        synchronised = data_scale(scene).views_per_timestamp >= 2
        if trim is not None and synchronised and (said := crop_field(model, optimizer, trim)):
            self.say(said)

    def revisit(
        self, step: int, state: DensifyState, final: bool = False, demote: bool = True
    ) -> None:
        """Revisit the split (`dyngs.engine.motion.revisit`) with the statistics in `state`;
        `demote=False` only promotes (while the window widens)."""
        cfg, model = self.config, self.model
        was_dynamic = model.any_dynamic()
        # A static Gaussian's region "keeps an error" when its screen gradient is high enough
        # to densify for and its canonical gradient consistently asks for a velocity.
        mean_gradient = state.grad_sum / state.count.clamp_min(1)
        coherence = max(cfg.motion.pull_coherence, schedules.chance_coherence(self.data.num_train))
        wants_motion = (mean_gradient >= cfg.densify.grad_threshold) & (
            state.pull_coherence() >= coherence
        )
        pixels_move = None
        if final:  # nothing is left to learn: only measured motion decides
            wants_motion[:] = False
        elif self.fixed_motion is not None:
            # Fixed cameras: a Gaussian where most of the cameras that see it see pixels
            # change is dynamic. Asked of the Gaussians as they are at each revisit, not
            # only at the end of the warm-up: Gaussians densify onto what moves later.
            means = model.canonical.means.detach()
            pixels_move = self.fixed_motion.evidence(means, cfg.motion)
        times = self.times
        if not demote:  # the field has learned nothing past the window yet
            window = schedules.time_window(cfg, step)
            seen = [t for _, t in self.data.train_poses(window)]
            times = sample_times(torch.tensor(seen, dtype=torch.float64), cfg.motion.samples)
        args = (cfg.motion, times, self.pixel_size, wants_motion, pixels_move, demote)
        became_static, became_dynamic = revisit(model, *args)
        self.writer.scalar("motion/became_static", became_static, step)
        self.writer.scalar("motion/became_dynamic", became_dynamic, step)
        if was_dynamic and not model.any_dynamic():
            self.say(
                f"[motion] nothing in this scene moves more than {cfg.motion.static_pixels}"
                " px: training on as a static scene, without the deformation field"
            )


def crop_field(
    model: DynamicGaussians, optimizer: torch.optim.Optimizer, trim: float = 0.0
) -> str | None:
    """Cut the field to the span of the Gaussians that query it (`trim`: between those
    quantiles of each axis; `Croppable.crop_to`); Adam's moments are cut alike, so a
    resumed run goes on. Returns what to say of it (None: nothing was cut)."""
    field = model.field
    if not isinstance(field, Croppable) or not model.any_dynamic():
        return None
    before = model_bytes(model)
    old = list(field.parameters())
    with torch.no_grad():
        remap = field.crop_to(model.canonical.means[model.dynamic], trim)
    if remap is None:
        return None
    replace_params(optimizer, old, list(field.parameters()), remap)
    quantiles = f" ({100 * trim:g}-{100 - 100 * trim:g} % along each axis)" if trim > 0 else ""
    return (
        f"[motion] field cut to the span of the dynamic Gaussians{quantiles}: model "
        f"{before / 2**20:.2f} → {model_bytes(model) / 2**20:.2f} MiB"
    )


@torch.no_grad()
def largest_shares(
    model: DynamicGaussians,
    renderer: ContributionRenderer,
    poses: list[tuple[int, Camera, float]],
    background: Tensor,
    importance: Tensor,
) -> None:
    """Raise `importance` in place to each Gaussian's share of every pose's view, in the
    whole view's pixels. A pose (factor, camera, t) is rendered at 1/factor of the camera's
    size, its shares scaled by the pixels it stands for. The poses come in time order: the
    views of one time (its cameras) share one deformation."""
    drawn: tuple[float, Gaussians] | None = None
    for factor, camera, t in poses:
        if drawn is None or drawn[0] != t:
            drawn = (t, model.at(t, absent_below=ABSENT_BELOW))
        view = camera if factor == 1 else camera.scaled(1.0 / factor)
        out = renderer.with_contribution(drawn[1], view, background)
        assert out.contribution is not None
        share = out.contribution.to(importance.dtype)
        if view is not camera:
            share = share * (camera.width * camera.height / (view.width * view.height))
        torch.maximum(importance, share, out=importance)


def densify_statistics(
    lifecycle: Lifecycle,
    out: RenderOutput,
    batch: TrainBatch,
    means_grad: Tensor | None,
    views: int,
) -> StepStatistics | None:
    """The densification statistics (`densify.view_statistics`) of the view `batch` drawn
    as `out`, under the lifecycle's config; a coarse view's radii are counted in its whole
    view's pixels. A renderer that cannot measure the absolute gradient makes the run
    densify by the gradient against its own threshold (`lifecycle.config` changes), said
    once."""
    config = lifecycle.config
    if config.densify.absgrad and out.means2d_absgrad is None:
        densify = dataclasses.replace(config.densify, absgrad=False)
        lifecycle.config = config = dataclasses.replace(config, densify=densify)
        lifecycle.console.print(
            "[densify] the renderer cannot measure the absolute gradient: densifying "
            "by the gradient (--densify.grad-threshold)",
            highlight=False,
            markup=False,
        )
    camera = batch.camera
    pixel_scale = 1.0 if batch.full is None else batch.full.camera.width / camera.width
    return view_statistics(out, camera.width, camera.height, means_grad, batch.time, views,
                           config.densify.absgrad, pixel_scale)  # fmt: skip

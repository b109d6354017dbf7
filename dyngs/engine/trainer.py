"""The training loop. `Trainer.train_step` is the whole of one step, in one place."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import torch
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from torch import Tensor

from dyngs.config import LossConfig, TrainConfig
from dyngs.datamanagers.base import SceneData
from dyngs.datamanagers.datamanager import DataManager, TrainBatch, load_scene
from dyngs.datamanagers.fixed_cameras import FixedCameras
from dyngs.engine.capacity import pixel_footprint, resolve_capacity
from dyngs.engine.checkpoint import load_checkpoint, save_checkpoint
from dyngs.engine.densify import (
    DensifyState,
    TopologyChange,
    accumulate,
    apply_topology,
    is_refine_step,
    is_reset_step,
    plan_refinement,
    probe_band,
    reset_opacity_logits,
)
from dyngs.engine.evaluate import evaluate
from dyngs.engine.interrupt import deferred_interrupt
from dyngs.engine.motion import FixedCameraMotion, model_bytes, revisit, sample_times
from dyngs.engine.optim import build_optimizer, replace_params, set_learning_rates
from dyngs.engine.writer import Writer
from dyngs.errors import ConfigError, UserError
from dyngs.fields.base import PlaneGrids
from dyngs.losses.arap import arap_loss, neighbor_weights
from dyngs.losses.photometric import photometric
from dyngs.losses.temporal import time_l1_to_static, time_smoothness
from dyngs.losses.tv import plane_tv
from dyngs.metrics import psnr
from dyngs.model import CanonicalGaussians, DynamicGaussians
from dyngs.neighbors import knn
from dyngs.renderers import renderer_name
from dyngs.renderers.base import ContributionRenderer, Renderer, RenderOutput

CHECKPOINT_NAME = "checkpoint.pt"


@contextmanager
def native_convolutions() -> Iterator[None]:
    """Run without oneDNN convolutions: ATen's own are faster for SSIM's small depthwise
    kernels, and unlike oneDNN's their results do not depend on memory alignment."""
    previous = torch._C._get_mkldnn_enabled()
    torch._C._set_mkldnn_enabled(False)
    try:
        yield
    finally:
        torch._C._set_mkldnn_enabled(previous)


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"--device {name}: no CUDA device is available")
    return device


def camera_extent(scene: SceneData) -> float:
    """Radius of the training cameras around their centroid, ×1.1 (3DGS's scene extent);
    scales position learning rates and densification thresholds."""
    centers = torch.stack([c.center.double() for c in scene.train.cameras])
    radius = float((centers - centers.mean(0)).norm(dim=-1).max()) * 1.1
    return radius if radius > 0 else scene.scene_box.diagonal / 2


@dataclass
class StepStats:
    loss: Tensor
    terms: dict[str, Tensor]
    out: RenderOutput
    batch: TrainBatch
    applied: bool = True
    """False when the step was skipped for a non-finite loss or gradient."""


class TrainingDiverged(UserError):
    """Too many consecutive steps had non-finite losses or gradients."""


def regularization(weights: LossConfig, planes: PlaneGrids) -> dict[str, Tensor]:
    """Plane regularizers (K-Planes); terms with weight 0 are not computed at all."""
    terms: dict[str, Tensor] = {}
    if weights.plane_tv > 0 and planes.spatial:
        terms["plane_tv"] = weights.plane_tv * plane_tv(planes.spatial)
    if weights.time_smoothness > 0 and planes.temporal:
        terms["time_smoothness"] = weights.time_smoothness * time_smoothness(planes.temporal)
    if weights.time_l1 > 0 and planes.temporal:
        terms["time_l1"] = weights.time_l1 * time_l1_to_static(planes.temporal)
    return terms


class Trainer:
    def __init__(
        self,
        config: TrainConfig,
        run_dir: Path,
        writer: Writer,
        console: Console | None = None,
        scene: SceneData | None = None,
    ) -> None:
        self.config = config
        self.run_dir = run_dir
        self.writer = writer
        self.console = console or Console()
        self.device = resolve_device(config.device)
        torch.manual_seed(config.seed)
        self.generator = torch.Generator().manual_seed(config.seed)

        # The renderer first: a machine that cannot run it should say so before any loading.
        self.renderer: Renderer = config.renderer.build()
        self.scene = scene or load_scene(config.data, config.dataset, seed=config.seed)
        self.config = config = resolve_capacity(config, self.scene)
        self.data = DataManager(self.scene, config.dataset, self.device, self.generator)
        self.background = self.scene.background.to(self.device, torch.float32)
        self.extent = camera_extent(self.scene)

        canonical = CanonicalGaussians.from_points(
            self.scene.points, self.scene.point_colors, config.gaussians, self.generator
        )
        field = config.field.build(self.scene.scene_box, generator=self.generator)
        head = config.head.build(field.out_dim, self.scene.scene_box, generator=self.generator)
        self.model = DynamicGaussians(canonical, field, head, self.scene.scene_box).to(self.device)
        self.optimizer = build_optimizer(self.model, config.optim, self.extent)
        self.densify_state = DensifyState.zeros(len(canonical), self.device)
        self._arap: tuple[Tensor, Tensor] | None = None
        self.pixel_size = pixel_footprint(self.scene)
        self.motion_times = sample_times(self.scene.train.times, config.motion.samples)
        self.step = 0
        self.active_sh = 0
        # Gaussians the renderer culled for a non-finite parameter, summed over the steps
        # since the last log line (a device tensor: counting never waits for the device).
        self.nonfinite_culled = torch.zeros((), dtype=torch.long, device=self.device)
        self.train_seconds = 0.0
        self.deformation_seconds = 0.0
        self.importance_seconds = 0.0  # measuring importance before refinements
        self.skipped_steps = 0
        self.bad_streak = 0

    # ------------------------------------------------------------------ one step

    def probe_degree(self) -> int | None:
        """The SH band rendered frozen at zero to gather evidence for it, if any."""
        g = self.config.gaussians
        if g.sh_evidence > 0 and self.active_sh < g.sh_degree:
            return self.active_sh + 1
        return None

    def chance_coherence(self) -> float:
        """Chance alone makes a gradient summed over the views about 1/√views consistent;
        evidence must clear three times that."""
        return 3 / math.sqrt(max(len(self.scene.train), 1))

    def consider_sh_degree(self, step: int) -> None:
        """At each SH interval, raise the degree if the frozen band's evidence asks for it."""
        g = self.config.gaussians
        if self.active_sh >= g.sh_degree or step % max(g.sh_degree_interval, 1) != 0:
            return
        if g.sh_evidence <= 0:
            self.active_sh += 1
            return
        evidence = self.densify_state.sh_coherence()
        self.writer.scalar("sh/evidence", evidence, self.step)
        if evidence >= max(g.sh_evidence, self.chance_coherence()):
            self.active_sh += 1
            self.console.print(
                f"[sh] view-dependent error (evidence {evidence:.2f}): SH degree {self.active_sh}",
                highlight=False,
                markup=False,
            )

    def window_full_step(self) -> float:
        """First step at which the time window spans the whole sequence."""
        cfg = self.config
        return cfg.warmup_iters + cfg.time_ramp * cfg.max_iters

    def learning_progress(self, step: int) -> tuple[float, float | None]:
        """How far the rates have decayed: the run's progress, and the deformation's (from
        the step the time window is full) when `--optim.hold-deformation-rates`."""
        cfg = self.config
        progress = step / max(cfg.max_iters, 1)
        if not cfg.optim.hold_deformation_rates:
            return progress, None
        full = self.window_full_step()
        return progress, (step - full) / max(cfg.max_iters - full, 1)

    def time_window(self, step: int) -> float:
        """Latest time trained on at `step`: `warmup_time` through the warm-up, then widening
        linearly to 1 over `time_ramp` of the run."""
        cfg = self.config
        if step < cfg.warmup_iters:
            return cfg.warmup_time
        ramp = cfg.time_ramp * cfg.max_iters
        if ramp <= 0:
            return 1.0
        return min(1.0, cfg.warmup_time + (1 - cfg.warmup_time) * (step - cfg.warmup_iters) / ramp)

    def is_frontier_step(self, step: int) -> bool:
        """Whether this step trains on the newest part of a widening window: `frontier_share`
        of the steps, spread evenly (step s is one when ⌊(s + 1)·share⌋ > ⌊s·share⌋)."""
        share = self.config.frontier_share
        return (
            self.deforming(step)
            and self.time_window(step) < 1.0
            and math.floor((step + 1) * share) > math.floor(step * share)
        )

    def deforming(self, step: int) -> bool:
        return step >= self.config.warmup_iters

    def train_step(self, step: int) -> StepStats:
        with native_convolutions():
            return self._train_step(step)

    def _train_step(self, step: int) -> StepStats:
        """One iteration: a view, a render, the losses, a gradient step, densification."""
        cfg = self.config
        set_learning_rates(self.optimizer, *self.learning_progress(step))
        window = self.time_window(step)
        if self.is_frontier_step(step):
            batch = self.data.next_frontier(window, cfg.frontier_span)
        else:
            batch = self.data.next_train(max_time=window)
        deform = self.deforming(step) and self.model.any_dynamic()

        started = time.perf_counter()
        probe = self.probe_degree()
        gaussians = self.model.at(batch.time, probe or self.active_sh, deform=deform)
        self.deformation_seconds += time.perf_counter() - started if deform else 0.0
        if self.prunes_by_drawn_views() and isinstance(self.renderer, ContributionRenderer):
            out = self.renderer.with_contribution(gaussians, batch.camera, self.background)
        else:
            out = self.renderer(gaussians, batch.camera, self.background)
        self.nonfinite_culled += out.num_nonfinite.to(self.nonfinite_culled.device)

        weights = self.loss_weights(batch)
        terms = {"photometric": photometric(out.rgb, batch.image, cfg.losses.dssim, weights)}
        if deform:
            terms |= regularization(cfg.losses, self.model.field.planes())
            if cfg.losses.arap > 0:
                terms["arap"] = cfg.losses.arap * self.rigidity(gaussians.means, batch.time)
        loss = torch.stack(list(terms.values())).sum()
        loss.backward()
        self._quarantine_nonfinite_gaussians()

        # A step whose loss or gradients are not finite never reaches the parameters, the
        # optimizer's moments or the densification statistics (one host sync per step, as
        # AMP's GradScaler does).
        good = bool(self._all_finite(loss))
        if good:
            if probe is not None:
                probe_band(self.densify_state, self.model.canonical.sh_rest, probe)
            accumulate(
                self.densify_state,
                out,
                batch.camera.width,
                batch.camera.height,
                self.model.canonical.means.grad,
                batch.time,
            )
            self.optimizer.step()
            self.bad_streak = 0
        else:
            self.skipped_steps += 1
            self.bad_streak += 1
        self.optimizer.zero_grad(set_to_none=True)
        if self.bad_streak >= cfg.max_bad_steps:
            raise TrainingDiverged(
                f"training stopped at step {step}: {self.bad_streak} consecutive steps had a "
                f"non-finite loss or gradient; the last good checkpoint is {self.checkpoint_path()}"
            )
        if good:
            self.refine(step + 1)
        return StepStats(loss.detach(), {k: v.detach() for k, v in terms.items()}, out, batch, good)

    def _quarantine_nonfinite_gaussians(self) -> None:
        """Zero the gradients of Gaussians with a non-finite parameter. The renderer culls
        them, but activations still pass NaN back (exp(inf) · 0); left alone, one such
        Gaussian would make every step non-finite. Refinement prunes them."""
        c = self.model.canonical
        bad = ~c.finite_rows()
        for p in c.params().values():
            if p.grad is not None:
                p.grad.masked_fill_(bad.reshape(-1, *[1] * (p.dim() - 1)), 0.0)

    def _all_finite(self, loss: Tensor) -> Tensor:
        flags = [torch.isfinite(loss)]
        for group in self.optimizer.param_groups:
            flags += [torch.isfinite(p.grad).all() for p in group["params"] if p.grad is not None]
        return torch.stack(flags).all()

    def rigidity(self, means_now: Tensor, t: float) -> Tensor:
        """Neighbour distances at time t against those at another random time."""
        if self._arap is None:
            with torch.no_grad():
                canonical = self.model.canonical.means.detach()
                neighbors = knn(canonical, self.config.losses.arap_neighbors)
                d = (canonical[:, None] - canonical[neighbors]).norm(dim=-1)
                weights = neighbor_weights(canonical, neighbors, float(d.mean()) + 1e-12)
            self._arap = (neighbors, weights)
        neighbors, weights = self._arap
        other = float(torch.rand((), generator=self.generator))
        with torch.no_grad():
            means_other = self.model.at(other, 0, deform=True).means
        return arap_loss(means_now, means_other, neighbors, weights)

    # ------------------------------------------------------- static / dynamic

    @cached_property
    def fixed_cameras(self) -> FixedCameras | None:
        """The training views' fixed cameras and their temporal medians (None without any):
        they depend on the images only, so they are read once, when first asked for."""
        return FixedCameras.of(self.scene.train)

    @cached_property
    def fixed_motion(self) -> FixedCameraMotion | None:
        """What the fixed cameras see move (None without any)."""
        fixed = self.fixed_cameras
        return None if fixed is None else FixedCameraMotion.of(self.scene.train, fixed=fixed)

    def loss_weights(self, batch: TrainBatch) -> Tensor | None:
        """Per-pixel weights of the photometric loss: the dataset's mask with
        `--losses.masked`, times 1 + `--losses.change-weight` where a fixed camera sees a
        pixel differ from its usual content."""
        cfg = self.config
        mask = batch.mask if cfg.losses.masked else None
        if cfg.losses.change_weight == 0 or self.fixed_cameras is None:
            return mask
        changed = self.fixed_cameras.changed(batch.index, batch.image, cfg.motion.pixel_change)
        if changed is None:
            return mask
        weights = (1 + cfg.losses.change_weight * changed.to(batch.image.dtype))[..., None]
        return weights if mask is None else weights * mask

    def change_weight_note(self) -> str:
        """What `--losses.change-weight` does on this capture, for the log."""
        weight = self.config.losses.change_weight
        if self.fixed_cameras is None:
            return (
                f"warning: --losses.change-weight {weight:g} has no effect: no camera of "
                f"{self.scene.name} stays put at three or more times"
            )
        return (
            f"[loss] {len(self.fixed_cameras.views)} fixed cameras: pixels that differ from "
            f"their camera's temporal median count {1 + weight:g}× in the photometric loss"
        )

    def is_motion_step(self, step: int) -> bool:
        """Revisit the split every `motion.every` steps once training spans all times."""
        cfg = self.config
        return (
            cfg.motion.separate
            and self.deforming(step)
            and self.time_window(step) >= 1.0
            and step % cfg.motion.every == 0
        )

    def revisit_motion(self, final: bool = False) -> None:
        was_dynamic = self.model.any_dynamic()
        state = self.densify_state
        # A static Gaussian's region "keeps an error" when its screen gradient is high enough
        # to densify for and its canonical gradient consistently asks for a velocity.
        mean_gradient = state.grad_sum / state.count.clamp_min(1)
        wants_motion = (mean_gradient >= self.config.densify.grad_threshold) & (
            state.pull_coherence()
            >= max(self.config.motion.pull_coherence, self.chance_coherence())
        )
        pixels_move = None
        if final:  # nothing is left to learn: only measured motion decides
            wants_motion[:] = False
        else:
            # Fixed cameras: a Gaussian where most of the cameras that see it see pixels
            # change is dynamic. Asked of the Gaussians as they are at each revisit, not at
            # the end of the warm-up: from a noisy initial cloud (the MuJoCo scenes) nothing
            # sits on the moving objects yet, and a split made then starved the field for
            # good (mujoco-collision, seed 1: 21.96 dB against 25.70 dB).
            if self.fixed_motion is not None:
                pixels_move = self.fixed_motion.evidence(
                    self.model.canonical.means.detach(), self.config.motion
                )
        became_static, became_dynamic = revisit(
            self.model,
            self.config.motion,
            self.motion_times,
            self.pixel_size,
            wants_motion,
            pixels_move,
        )
        self.writer.scalar("motion/became_static", became_static, self.step)
        self.writer.scalar("motion/became_dynamic", became_dynamic, self.step)
        self.announce_static_scene(was_dynamic)

    def crop_field(self) -> None:
        """Cut the field to the span of the Gaussians that query it, once they stop moving
        (the end of training); Adam's moments are cut alike, so a resumed run goes on."""
        crop_to = getattr(self.model.field, "crop_to", None)
        if not self.config.motion.crop_field or crop_to is None or not self.model.any_dynamic():
            return
        before = model_bytes(self.model, self.active_sh)
        old = list(self.model.field.parameters())
        with torch.no_grad():
            remap = crop_to(self.model.canonical.means[self.model.dynamic])
        if remap is None:
            return
        replace_params(self.optimizer, old, list(self.model.field.parameters()), remap)
        after = model_bytes(self.model, self.active_sh)
        self.console.print(
            f"[motion] field cut to the span of the dynamic Gaussians: model "
            f"{before / 2**20:.2f} → {after / 2**20:.2f} MiB",
            highlight=False,
            markup=False,
        )

    def announce_static_scene(self, was_dynamic: bool) -> None:
        if was_dynamic and not self.model.any_dynamic():
            self.console.print(
                f"[motion] nothing in this scene moves more than {self.config.motion.static_pixels}"
                " px: training on as a static scene, without the deformation field",
                highlight=False,
                markup=False,
            )

    def dynamic_fraction(self) -> float:
        """Share of the Gaussians deformed now (none during the static warm-up)."""
        return self.model.dynamic_fraction() if self.deforming(self.step) else 0.0

    # ------------------------------------------------------------ densification

    def refine(self, step: int) -> None:
        cfg = self.config
        if self.is_motion_step(step):
            self.revisit_motion()
        self.consider_sh_degree(step)
        if is_refine_step(cfg.densify, step, cfg.max_iters):
            if cfg.densify.prune_importance > 0 and cfg.densify.importance_views > 0:
                started = time.perf_counter()
                self.densify_state.importance = self.measure_importance(step)
                self.importance_seconds += time.perf_counter() - started
            plan = plan_refinement(
                cfg.densify,
                self.model,
                self.densify_state,
                step,
                self.extent,
                self.generator,
                cfg.max_iters,
            )
            if plan is not None:
                self.apply_topology(*plan)
            self.densify_state = DensifyState.zeros(len(self.model.canonical), self.device)
        if is_reset_step(cfg.densify, step, cfg.max_iters):
            logits = self.model.canonical.opacity_logits
            with torch.no_grad():
                logits.copy_(reset_opacity_logits(logits, cfg.densify.reset_opacity))
            for moment in self.optimizer.state.get(logits, {}).values():
                if isinstance(moment, Tensor) and moment.ndim > 0:
                    moment.zero_()

    def prunes_by_drawn_views(self) -> bool:
        """Whether importance is the largest share of the views drawn since the last
        refinement (`--densify.importance-views 0`), so that every training step must
        measure its view's contributions. Otherwise no step does: `measure_importance`
        renders the window's views just before each refinement."""
        d = self.config.densify
        return d.prune_importance > 0 and d.importance_views == 0

    def measure_importance(self, step: int) -> Tensor:
        """Each Gaussian's largest share (blending weight summed over pixels) of any of
        `--densify.importance-views` training views of the time window at `step`, rendered
        now without gradient. The views drawn since the last refinement were both a
        sample and stale: on the demo, once the window is half open, 13-30 % of its views
        had not been drawn, and a Gaussian that only those need looked unimportant; and a
        view drawn 99 steps ago vouched for a Gaussian that has since faded
        (docs/CAPACITY.md)."""
        cfg = self.config
        deform = self.deforming(step) and self.model.any_dynamic()
        importance = torch.zeros(len(self.model.canonical), device=self.device)
        poses = self.data.train_poses(self.time_window(step), cfg.densify.importance_views)
        if not isinstance(self.renderer, ContributionRenderer):
            return importance.fill_(math.inf)  # a renderer that cannot measure it never prunes
        with torch.no_grad():
            for camera, t in poses:
                gaussians = self.model.at(t, self.active_sh, deform=deform)
                out = self.renderer.with_contribution(gaussians, camera, self.background)
                assert out.contribution is not None
                importance = torch.maximum(importance, out.contribution.to(importance.dtype))
        return importance

    def apply_topology(self, change: TopologyChange, values: dict[str, Tensor]) -> None:
        apply_topology(self.model, self.optimizer, change, values)
        self._arap = None  # neighbours are recomputed on the new set

    # --------------------------------------------------------------- the loop

    def schedule_warning(self) -> str | None:
        """A one-line warning when the run is too short for densification to happen."""
        cfg, d = self.config, self.config.densify
        if cfg.max_iters > 0 and d.refine_start > d.refine_stop * cfg.max_iters:
            return (
                f"warning: no densification in this run: it would start at step "
                f"{d.refine_start} and stop at {d.refine_stop:g} × {cfg.max_iters} = "
                f"{d.refine_stop * cfg.max_iters:g} (lower --densify.refine-start)"
            )
        return None

    def train(self) -> dict[str, Any]:
        cfg = self.config
        warning = self.schedule_warning()
        if warning is not None and self.step < cfg.max_iters:
            self.console.print(warning, highlight=False, markup=False)
        if cfg.losses.change_weight > 0 and self.step < cfg.max_iters:
            self.console.print(self.change_weight_note(), highlight=False, markup=False)
        columns = (
            TextColumn("[bold]train"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[info]}"),
            TimeRemainingColumn(),
        )
        info = ""
        with (
            deferred_interrupt() as interrupted,
            Progress(*columns, console=self.console, transient=False) as progress,
        ):
            task = progress.add_task("train", total=cfg.max_iters, completed=self.step, info=info)
            window_start, window_steps = time.perf_counter(), 0
            try:
                while self.step < cfg.max_iters:
                    started = time.perf_counter()
                    stats = self.train_step(self.step)
                    self.step += 1
                    self.train_seconds += time.perf_counter() - started
                    window_steps += 1
                    if self.step % cfg.log_every == 0 or self.step == cfg.max_iters:
                        rate = window_steps / max(time.perf_counter() - window_start, 1e-9)
                        info = self.log(stats, rate)
                        window_start, window_steps = time.perf_counter(), 0
                        if not self.console.is_terminal:  # logs and CI get plain lines
                            self.console.print(
                                f"step {self.step}/{cfg.max_iters}  {info}", highlight=False
                            )
                    if cfg.image_every > 0 and self.step % cfg.image_every == 0:
                        self.writer.image("train/render", stats.out.rgb, self.step)
                        self.writer.image("train/ground_truth", stats.batch.image, self.step)
                    if cfg.checkpoint_every > 0 and self.step % cfg.checkpoint_every == 0:
                        self.save()
                    progress.update(task, completed=self.step, info=info)
                    if interrupted():  # Ctrl-C during the step: stop now that it is whole
                        raise KeyboardInterrupt
            except KeyboardInterrupt:
                self.save()
                self.writer.flush()
                self.console.print(
                    f"[yellow]interrupted at step {self.step}; checkpoint saved in {self.run_dir}. "
                    f"Resume with: dyngs-train --resume {self.run_dir}"
                )
                raise
        if cfg.motion.separate and self.deforming(self.step):
            self.revisit_motion(final=True)
        self.crop_field()
        self.save()
        return self.evaluate()

    def log(self, stats: StepStats, rate: float) -> str:
        loss = float(stats.loss)
        quality = float(psnr(stats.out.rgb.detach(), stats.batch.image))
        n = len(self.model.canonical)
        capacity = self.capacity()
        w = self.writer
        w.scalar("train/loss", loss, self.step)
        for name, value in stats.terms.items():
            w.scalar(f"train/loss/{name}", float(value), self.step)
        w.scalar("train/psnr", quality, self.step)
        w.scalar("train/num_gaussians", n, self.step)
        for key, amount in capacity.items():
            w.scalar(f"train/{key}", amount, self.step)
        w.scalar("train/skipped_steps", self.skipped_steps, self.step)
        w.scalar("train/importance_seconds", self.importance_seconds, self.step)
        w.scalar("train/iterations_per_second", rate, self.step)
        for group in self.optimizer.param_groups:
            w.scalar(f"learning_rate/{group['name']}", group["lr"], self.step)
        culled = int(self.nonfinite_culled)
        self.nonfinite_culled.zero_()
        w.scalar("train/nonfinite_gaussians_culled", culled, self.step)
        skipped = f"  skipped {self.skipped_steps}" if self.skipped_steps else ""
        skipped += f"  culled non-finite {culled}" if culled else ""
        return (
            f"loss {loss:.4f}  psnr {quality:5.2f}  gaussians {n:,}  "
            f"dynamic {capacity['dynamic_fraction']:.1%}  "
            f"{capacity['model_bytes'] / 2**20:.1f} MiB  {rate:.1f} it/s{skipped}"
        )

    def capacity(self) -> dict[str, float]:
        """What the model costs: dynamic share, stored size, time spent deforming."""
        return {
            "dynamic_fraction": self.dynamic_fraction(),
            "model_bytes": model_bytes(self.model, self.active_sh),
            "deformation_seconds": self.deformation_seconds,
            "deformation_share": self.deformation_seconds / max(self.train_seconds, 1e-9),
        }

    def evaluate(self) -> dict[str, Any]:
        split = self.config.eval_split
        metrics = evaluate(
            self.model,
            self.renderer,
            self.data,
            split,
            sh_degree=self.active_sh,
            deform=self.deforming(self.step),
            image_dir=self.run_dir / split,
            device=self.device,
            console=self.console,
        )
        metrics |= {
            "num_gaussians": len(self.model.canonical),
            **self.capacity(),
            "static_scene": self.config.motion.separate and not self.model.any_dynamic(),
            "train_seconds": self.train_seconds,
            "importance_seconds": self.importance_seconds,
            "iterations": self.step,
            "skipped_steps": self.skipped_steps,
            "renderer": renderer_name(self.config.renderer),
            "device": str(self.device),
        }
        for key in ("psnr", "ssim", "lpips"):
            value = metrics.get(key)
            if value is not None and math.isfinite(value):
                self.writer.scalar(f"{split}/{key}", value, self.step)
        self.writer.flush()
        return metrics

    # ------------------------------------------------------------ checkpoints

    def checkpoint_path(self) -> Path:
        return self.run_dir / CHECKPOINT_NAME

    def save(self) -> None:
        save_checkpoint(
            self.checkpoint_path(),
            {
                "step": self.step,
                "active_sh": self.active_sh,
                "train_seconds": self.train_seconds,
                "deformation_seconds": self.deformation_seconds,
                "importance_seconds": self.importance_seconds,
                "skipped_steps": self.skipped_steps,
                "model": self.model.state_dict(),
                "optimizer": self.optimizer.state_dict(),
                "densify": self.densify_state.state_dict(),
                "data": self.data.state_dict(),
                "generator": self.generator.get_state(),
                "torch_rng": torch.get_rng_state(),
            },
        )

    def load(self, path: Path) -> None:
        state = load_checkpoint(path, self.device)
        self.model.load_state_dict(state["model"])
        # The parameters were replaced to fit the checkpoint's Gaussian count: rebuild the
        # optimizer around them before restoring its moments.
        self.optimizer = build_optimizer(self.model, self.config.optim, self.extent)
        self.optimizer.load_state_dict(state["optimizer"])
        self.densify_state = DensifyState.from_state_dict(state["densify"])
        self.data.load_state_dict(state["data"])
        self.generator.set_state(state["generator"].cpu())
        torch.set_rng_state(state["torch_rng"].cpu())
        self.step = int(state["step"])
        self.active_sh = int(state.get("active_sh", 0))
        self.train_seconds = float(state["train_seconds"])
        self.skipped_steps = int(state.get("skipped_steps", 0))
        self.deformation_seconds = float(state.get("deformation_seconds", 0.0))
        self.importance_seconds = float(state.get("importance_seconds", 0.0))
        self._arap = None

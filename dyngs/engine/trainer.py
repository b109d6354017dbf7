"""The training loop. `Trainer.train_step` is the whole of one step, in one place.

The parts it drives each live in their own module: when things happen
(`dyngs.engine.schedules`), the loss as named terms (`dyngs.engine.objective`), what
happens to the model between steps (`dyngs.engine.lifecycle`), what is reported
(`dyngs.engine.report`).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from torch import Tensor

from dyngs.appearance import CameraColours
from dyngs.config import TrainConfig
from dyngs.configio import config_to_dict
from dyngs.datamanagers.base import SceneData
from dyngs.datamanagers.datamanager import DataManager, load_scene
from dyngs.engine import schedules
from dyngs.engine.batch import (
    ViewResult,
    backward_view,
    exchange,
    step_loss,
    step_statistics,
)
from dyngs.engine.budget import TimeBudget
from dyngs.engine.capacity import pixel_footprint, resolve_capacity, training_steps_why
from dyngs.engine.checkpoint import (
    load_checkpoint,
    restore_training,
    save_checkpoint,
    training_state,
)
from dyngs.engine.distributed import SINGLE, ProcessGroup, RankLost, check_batch
from dyngs.engine.evaluate import evaluate
from dyngs.engine.interrupt import deferred_interrupt
from dyngs.engine.lifecycle import Lifecycle, densify_statistics
from dyngs.engine.objective import Objective
from dyngs.engine.optim import build_optimizer, deformation_rate_scale, set_learning_rates
from dyngs.engine.report import Counters, StepStats, log_step, run_summary, write_metrics
from dyngs.engine.writer import Writer
from dyngs.errors import ConfigError, UserError
from dyngs.model import CanonicalGaussians, DynamicGaussians, subsample_points
from dyngs.renderers.base import Renderer

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


def initial_model(
    config: TrainConfig, scene: SceneData, generator: torch.Generator
) -> DynamicGaussians:
    """The model at step 0: a Gaussian at each of the scene's initial points (subsampled
    to the budget), the field and head drawn from `generator`."""
    points, colors, lifetimes = subsample_points(
        scene.points, scene.point_colors, config.gaussians.max_init_points, generator,
        scene.point_lifetimes,
    )  # fmt: skip
    model = DynamicGaussians.build(
        config.gaussians, config.field, config.head, scene.scene_box, len(points), generator
    )
    model.canonical.initialize(points, colors, config.gaussians, lifetimes)
    model.deforming = schedules.deforming(config, 0)
    if config.optim.camera_colours > 0:
        model.colours = CameraColours.for_split(scene.train)
    return model


def quarantine_nonfinite_gaussians(canonical: CanonicalGaussians) -> None:
    """Zero the gradients of Gaussians with a non-finite parameter. The renderer culls
    them, but activations still pass NaN back (exp(inf) · 0); left alone, one such
    Gaussian would make every step non-finite. Refinement prunes them."""
    bad = ~canonical.finite_rows()
    if bad.device.type == "cpu" and not bool(bad.any()):
        return  # the usual case: no pass over every gradient (on a GPU, no host sync)
    for p in canonical.params().values():
        if p.grad is not None:
            p.grad.masked_fill_(bad.reshape(-1, *[1] * (p.dim() - 1)), 0.0)


def time_noise(config: TrainConfig, step: int, spacing: float, generator: torch.Generator
               ) -> list[float]:  # fmt: skip
    """The shift of the model's time for each of a step's views (`--time-jitter`), drawn in
    view order. Nothing is drawn once the jitter is 0, so a run without it draws its
    views as before; every process draws them all (see `Objective.other_times`)."""
    scale = schedules.time_jitter(config, step) * spacing
    if scale == 0.0:
        return [0.0] * config.batch_views
    return [scale * float(torch.randn((), generator=generator)) for _ in range(config.batch_views)]


def all_finite(loss: Tensor, optimizer: torch.optim.Optimizer) -> Tensor:
    """Whether the loss and every gradient are finite (0-d, on the loss's device).

    The gradients are checked by the fused kernel AMP's GradScaler finds inf and NaN with,
    one call per device and dtype, where an `isfinite(...).all()` per tensor made some
    forty small passes a step. Its scale is 1, which leaves every value as it is.
    tests/engine/test_robustness.py holds it to the per-tensor check."""
    groups: dict[tuple[torch.device, torch.dtype], list[Tensor]] = {}
    for group in optimizer.param_groups:
        for p in group["params"]:
            if p.grad is not None:
                groups.setdefault((p.grad.device, p.grad.dtype), []).append(p.grad)
    finite = torch.isfinite(loss)
    for (device, _), grads in groups.items():
        found = torch.zeros(1, device=device)
        torch._amp_foreach_non_finite_check_and_unscale_(grads, found, torch.ones(1, device=device))
        finite = finite & (found[0] == 0).to(finite.device)
    return finite


PROGRESS_COLUMNS = (
    TextColumn("[bold]train"),
    BarColumn(),
    MofNCompleteColumn(),
    TextColumn("{task.fields[info]}"),
    TimeRemainingColumn(),
)


StepHook = Callable[["Trainer", StepStats], None]
"""Called after every training step with the trainer and the step's stats, in the training
thread (a viewer shows the model, and may pause training by not returning)."""


class TrainingDiverged(UserError):
    """Too many consecutive steps had non-finite losses or gradients."""


class Trainer:
    """Trains one run: builds every part from the config, then `train` steps through the
    schedule, checkpoints, and evaluates at the end."""

    def __init__(
        self,
        config: TrainConfig,
        run_dir: Path,
        writer: Writer,
        console: Console | None = None,
        scene: SceneData | None = None,
        hooks: Sequence[StepHook] = (),
        group: ProcessGroup = SINGLE,
    ) -> None:
        self.run_dir = run_dir
        self.hooks = list(hooks)
        self.writer = writer
        self.console = console or Console()
        self.group = group
        check_batch(group.size, config.batch_views)
        self.device = group.device(resolve_device(config.device))
        torch.manual_seed(config.seed)
        self.generator = torch.Generator().manual_seed(config.seed)
        # The renderer first: a machine that cannot run it should say so before any loading.
        self.renderer: Renderer = config.renderer.build()
        self.scene = scene or load_scene(config.data, config.dataset, seed=config.seed)
        self.sized_steps = config.max_iters is None
        config = resolve_capacity(config, self.scene)  # `self.config` once the lifecycle holds it
        self.budget = TimeBudget.of(config.time_budget, config.steps, self.sized_steps)
        group.check_same(json.dumps(config_to_dict(config), sort_keys=True), "configs")
        self.data = DataManager(self.scene, config.dataset, self.device, self.generator,
                                config.batch_views, (group.rank, group.size))  # fmt: skip
        self.extent = camera_extent(self.scene)
        self.model = initial_model(config, self.scene, self.generator).to(self.device)
        self.optimizer = build_optimizer(self.model, config.optim, self.extent)
        self.objective = Objective(
            config.losses, self.data, config.motion.pixel_change, self.generator
        )
        self.lifecycle = Lifecycle(
            config, self.model, self.data, writer, self.console, self.generator,
            self.extent, pixel_footprint(self.scene), self.objective.on_topology, group,
        )  # fmt: skip
        if group.distributed:  # what reads every image has: keep only this rank's share
            self.lifecycle.read_every_image()
            self.data.release_others()
            self.scene = self.data.scene
        self.step = 0
        self.counters = Counters()
        # Gaussians the renderer culled for a non-finite parameter, summed over the steps
        # since the last log line (a device tensor: counting never waits for the device).
        self.nonfinite_culled = torch.zeros((), dtype=torch.long, device=self.device)

    @property
    def config(self) -> TrainConfig:
        """The run's configuration as the lifecycle holds it: training may change it."""
        return self.lifecycle.config

    # ------------------------------------------------------------------ one step

    def train_step(self, step: int) -> StepStats:
        with native_convolutions():
            return self._train_step(step)

    def _train_step(self, step: int) -> StepStats:
        """One iteration: the step's views (this rank's share), each rendered and its loss
        sent backward, the gradients summed over the ranks, a gradient step, then whatever
        the lifecycle has due (refinement, motion revisits, SH degree)."""
        cfg, model = self.config, self.model
        set_learning_rates(self.optimizer, *schedules.learning_progress(cfg, step))
        model.deforming = schedules.deforming(cfg, step)
        picks = self.next_views(step)
        probe = self.lifecycle.probe_degree()
        others = self.group.share(self.objective.other_times(model, cfg.batch_views))
        shifts = self.group.share(time_noise(cfg, step, self.data.time_spacing, self.generator))
        views = [self._view(step, probe, *draw) for draw in zip(picks, others, shifts, strict=True)]
        loss = step_loss(views, cfg.batch_views)
        quarantine_nonfinite_gaussians(model.canonical)
        stats = exchange(self.group, self.optimizer, loss, step_statistics(views),
                         len(model.canonical))  # fmt: skip

        # A step whose loss or gradients are not finite never reaches the parameters, the
        # optimizer's moments or the densification statistics (one host sync per step, as
        # AMP's GradScaler does). Every rank holds the same sums, so all decide alike.
        good = bool(all_finite(loss, self.optimizer))
        if good:
            self.lifecycle.gather(stats, probe)
            self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        self._count(step, good)
        # The model's state describes it as the next step will use it (and a checkpoint
        # written now, or the evaluation after the last step, too).
        model.deforming = schedules.deforming(cfg, step + 1)
        if good:
            self.lifecycle.after_step(step + 1, self.optimizer, self.renderer)
        first = views[0]
        return StepStats(loss.detach(), first.terms, first.out, first.batch, good)

    def _view(
        self, step: int, probe: int | None, index: int, other: float | None, shift: float
    ) -> ViewResult:
        """Training view `index`, the model at its time + `shift` (in [0, 1]): drawn, its loss
        (over the step's view count) sent backward, its densification statistics taken."""
        model, views = self.model, self.config.batch_views
        whole = self.data.train_batch(index)
        batch = whole.coarse(schedules.coarse_factor(self.config, step, whole.camera))
        started, t = time.perf_counter(), min(1.0, max(0.0, batch.time + shift))
        gaussians = model.at(t, sh_degree=probe, absent_below=self.objective.absent_below)
        self.counters.deformation_seconds += time.perf_counter() - started if model.deforms else 0
        out = self.lifecycle.render(self.renderer, gaussians, batch.camera, self.data.background)
        self.nonfinite_culled += out.num_nonfinite.to(self.nonfinite_culled.device)
        terms = self.objective.terms(model, out, batch, gaussians, step, other)
        loss = torch.stack(list(terms.values())).sum()
        means_grad = backward_view(loss if views == 1 else loss / views, model.canonical.means)
        if means_grad is not None:  # as the step's gradient will be (quarantine_nonfinite…)
            means_grad = means_grad.masked_fill(~model.canonical.finite_rows()[:, None], 0.0)
        stats = densify_statistics(self.lifecycle, out, batch, means_grad, views)
        return ViewResult(loss.detach(), {k: v.detach() for k, v in terms.items()}, out, batch,
                          stats)  # fmt: skip

    def next_views(self, step: int) -> list[int]:
        """This rank's share of the step's training views (of all of them with one
        process): from the newest part of the time window on frontier steps, else from
        anywhere in it. Every rank draws every view, so all stay in step."""
        window = schedules.time_window(self.config, step)
        span = self.config.frontier_span if schedules.is_frontier_step(self.config, step) else None
        return self.group.share(self.data.next_views(window, span))

    def _count(self, step: int, good: bool) -> None:
        """Count a skipped step; a streak of `--max-bad-steps` stops the run."""
        if (streak := self.counters.record(good)) >= self.config.max_bad_steps:
            raise TrainingDiverged(
                f"training stopped at step {step}: {streak} consecutive steps had a non-finite "
                f"loss or gradient; the last good checkpoint is {self.checkpoint_path()}"
            )

    # --------------------------------------------------------------- the loop

    def notes(self) -> list[str]:
        """What a run says before its first step: settings that will not do what they seem."""
        cfg = self.config
        if self.step >= cfg.steps:
            return []
        sized = training_steps_why(self.scene) if self.sized_steps else None
        notes = [*schedules.plan_notes(cfg, sized), self.lifecycle.importance_note(self.renderer)]
        notes.append(self.objective.change_weight_note() if cfg.losses.change_weight > 0 else None)
        notes.append(schedules.coarse_note(cfg, [camera for camera, _ in self.data.train_poses()]))
        notes.append(self.model.colours.note() if self.model.colours is not None else None)
        return [note for note in notes if note is not None]

    def train(self) -> dict[str, Any]:
        for note in self.notes():
            self.console.print(note, highlight=False, markup=False)
        with (
            deferred_interrupt() as interrupted,
            Progress(*PROGRESS_COLUMNS, console=self.console, transient=False) as progress,
        ):
            task = progress.add_task("train", total=self.config.steps, completed=self.step, info="")

            def show(info: str) -> None:
                progress.update(task, completed=self.step, total=self.config.steps, info=info)

            try:
                self._loop(show, interrupted)
            except RankLost as lost:
                raise lost.stopped(self.step, self.run_dir) from lost
            except KeyboardInterrupt:
                self.save()
                self.writer.flush()
                self.console.print(
                    f"[yellow]interrupted at step {self.step}; checkpoint saved in {self.run_dir}. "
                    f"Resume with: dyngs-train --resume {self.run_dir}"
                )
                raise
        self.model.deforming = schedules.deforming(self.config, self.step)
        self.lifecycle.finish(self.step, self.optimizer)
        self.save()
        return self.evaluate() if self.group.is_main else {}

    def _loop(self, show: Callable[[str], None], interrupted: Callable[[], bool]) -> None:
        """Steps until `max_iters`: logs, images and checkpoints at their intervals."""
        window_start, window_steps, info = time.perf_counter(), 0, ""
        while self.step < self.config.steps:
            cfg = self.config
            started = time.perf_counter()
            stats = self.train_step(self.step)
            self.step += 1
            self.counters.train_seconds += time.perf_counter() - started
            window_steps += 1
            if self.step % cfg.log_every == 0 or self.step == cfg.steps:
                rate = window_steps / max(time.perf_counter() - window_start, 1e-9)
                info = self.log(stats, rate)
                window_start, window_steps = time.perf_counter(), 0
                if not self.console.is_terminal:  # logs and CI get plain lines
                    self.console.print(f"step {self.step}/{cfg.steps}  {info}", highlight=False)
                self.replan()
            if cfg.image_every > 0 and self.step % cfg.image_every == 0:
                self.writer.image("train/render", stats.out.rgb, self.step)
                self.writer.image("train/ground_truth", stats.batch.image, self.step)
            if cfg.checkpoint_every > 0 and self.step % cfg.checkpoint_every == 0:
                self.save()
            show(info)
            for hook in self.hooks:
                hook(self, stats)
            if interrupted():  # Ctrl-C during the step: stop now that it is whole
                raise KeyboardInterrupt

    def replan(self) -> None:
        """`--time-budget`: after the warm-up, re-plan the step count (see budget.py)."""
        if self.budget is None or not schedules.deforming(self.config, self.step):
            return
        budget, seconds = self.budget, self.counters.train_seconds
        # Rank 0's measured rate decides for every rank: all must plan the same steps.
        planned = self.group.decide(lambda: budget.plan(self.step, seconds, self.config.steps))
        if planned is not None:
            self.lifecycle.config = schedules.repaced(self.config, self.step, planned)
            scale = deformation_rate_scale(self.config.optim, planned)
            said = self.budget.said(self.step, self.counters.train_seconds, planned, scale)
            self.console.print(said, highlight=False, markup=False)

    def log(self, stats: StepStats, rate: float) -> str:
        """Write the scalars of the last step and return its progress line."""
        culled = int(self.nonfinite_culled)
        self.nonfinite_culled.zero_()
        extra = {
            **{f"train/{name}": value for name, value in self.lifecycle.seconds().items()},
            "train/iterations_per_second": rate,
            "train/nonfinite_gaussians_culled": culled,
        }
        return log_step(self.writer, self.step, stats, self.model, self.optimizer,
                        self.counters, extra)  # fmt: skip

    def evaluate(self) -> dict[str, Any]:
        split = self.config.eval_split
        metrics = evaluate(self.model, self.renderer, self.data, split, self.run_dir / split,
                           self.device, self.console)  # fmt: skip
        metrics |= run_summary(self.model, self.counters, self.config, self.step, self.device,
                               **self.lifecycle.seconds())  # fmt: skip
        write_metrics(self.writer, split, metrics, self.step)
        return metrics

    def checkpoint_path(self) -> Path:
        return self.run_dir / CHECKPOINT_NAME

    def save(self) -> None:
        """The checkpoint, written by rank 0 alone (every rank holds the same state)."""
        if self.group.is_main:
            save_checkpoint(self.checkpoint_path(), training_state(self))

    def load(self, path: Path) -> None:
        restore_training(self, load_checkpoint(path, self.device))

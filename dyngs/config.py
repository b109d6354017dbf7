"""The training config: one frozen dataclass composing every component's config.

Each component config builds its component (`build(...)`); swappable parts are tagged
unions the CLI offers as subcommands (`renderer:cpu-reference`, `field:mlp`, …),
generated from the registries (`dyngs.registry`), so that a field, head or renderer an
installed package registers is offered beside the built-in ones. The docstring under
each field is its `--help` text.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import tyro

from dyngs.datamanagers.datamanager import DataConfig
from dyngs.engine.densify import DensifyConfig
from dyngs.engine.motion import MotionConfig
from dyngs.engine.optim import OptimConfig
from dyngs.errors import ConfigError
from dyngs.fields import FIELDS, HEADS, DeformationHeadConfig, FieldSpec, HeadSpec, HexPlaneConfig
from dyngs.model import GaussianConfig
from dyngs.registry import tyro_union
from dyngs.renderers import RENDERERS, CpuReferenceConfig, RendererSpec

if TYPE_CHECKING:  # the type checker sees the protocols every member satisfies
    FieldConfig = FieldSpec
    HeadConfig = HeadSpec
    RendererConfig = RendererSpec
else:  # the command line sees every registered config, plugins included
    FieldConfig = tyro_union(FIELDS)
    HeadConfig = tyro_union(HEADS)
    RendererConfig = tyro_union(RENDERERS)


@dataclass(frozen=True)
class LossConfig:
    """Loss weights; a weight of 0 switches its term off and skips its computation.

    The plane regularizers are means over planes (so a weight does not change meaning when
    scales are added); the defaults equal 4D Gaussian Splatting's weights (Wu et al. 2024:
    TV 1e-4, smoothness 1e-2, time L1 1e-4), which sum over its 2 scales × 3 planes and
    double the TV, converted to that form.
    """

    dssim: float = 0.2
    """Share of D-SSIM in the photometric loss, (1-λ)·L1 + λ·(1-SSIM) (Kerbl et al. 2023)."""
    masked: bool = False
    """Restrict the photometric loss to the dataset's masks (alpha or segmentation). Off by
    default: RGBA images are composited over the background, which must be learned too,
    or nothing stops floaters in front of it."""
    change_weight: float = 0.0
    """Fixed-camera captures: a pixel that differs from its camera's temporal median by more
    than --motion.pixel-change (something that is not usually there, such as a moving
    object) counts 1 + this many times in the photometric loss: DyNeRF's ray importance
    sampling by the global median (ISG; Li et al. 2022, Neural 3D Video Synthesis) as a
    loss weight, since a rasterizer draws every pixel anyway. Small moving objects are
    otherwise a few pixels in thousands and may be missed; where objects are found without
    it, the weights take fit from the rest of the image (measured in docs/TRAINING.md).
    No effect on other captures."""
    plane_tv: float = 1.2e-3
    """Total variation of the spatial feature planes (K-Planes)."""
    plane_roughness: float = 0.0
    """Roughness of the spatial feature planes: their TV divided, channel by channel, by the
    channel's variance over the plane, so that it smooths the deformation field without
    shrinking it (dyngs.losses.tv). Off by default: docs/ACCURACY.md measures it, with
    `--losses.plane-tv 0`, against the TV scene by scene."""
    time_smoothness: float = 6e-2
    """Second difference of the time planes along t (K-Planes)."""
    time_l1: float = 6e-4
    """L1 of the time planes toward 1, i.e. toward a static scene (K-Planes)."""
    arap: float = 0.0
    """Local rigidity: neighbour distances kept between the current and a random time."""
    arap_neighbors: int = 8
    """Canonical nearest neighbours per Gaussian for the rigidity term."""
    extra: dict[str, float] = dataclasses.field(default_factory=dict)
    """Extra loss terms by name and weight (`--losses.extra NAME WEIGHT …`), from those an
    installed package registers in the `dyngs.losses` entry-point group."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.dssim <= 1.0:
            raise ConfigError(f"--losses.dssim must be in [0, 1], got {self.dssim}")
        for name in (
            "change_weight",
            "plane_tv",
            "plane_roughness",
            "time_smoothness",
            "time_l1",
            "arap",
        ):
            value = getattr(self, name)
            if not value >= 0.0:  # NaN fails too
                flag = name.replace("_", "-")
                raise ConfigError(f"--losses.{flag} must be ≥ 0, got {value}")
        if self.arap_neighbors < 1:
            raise ConfigError(f"--losses.arap-neighbors must be ≥ 1, got {self.arap_neighbors}")
        for name, weight in self.extra.items():
            if not weight >= 0.0:
                raise ConfigError(f"--losses.extra {name}: weight must be ≥ 0, got {weight}")


@dataclass(frozen=True)
class CoarseConfig:
    """Coarse-to-fine training: the first part of the run draws each training view at a
    fraction of its resolution.

    Early on the model is a blur of the scene, and what the loss can teach it lies in the
    images' low frequencies; drawing a quarter of the pixels teaches that for a fraction of
    the step's cost (DashGaussian, Chen et al. 2025, schedule the resolution the same way
    to train 3DGS ~1.5× faster). A coarse view is the full one area-averaged by `factor`
    (as `--downscale` shrinks images) with its camera scaled alike, so nothing else
    changes: densification reads its gradients in NDC units and its sizes in full-size
    pixels. Only images large enough to keep `min-side` pixels take part: the small
    scenes (the demo, the MuJoCo scenes at ds 8) train as before."""

    until: float = 0.3
    """Fraction of the run (of its schedule, as `--time-ramp`) drawn coarse; 0 turns it off.
    0.3, the time window's ramp: on hfu-3cam (480×270) it trained 3000 steps to the same
    PSNR in a tenth less time, and in its 20-minute budget gained 1.2-1.4 dB in each of
    three seeds (docs/ACCURACY.md, "Large views drawn at half size for the first 30 % of
    the run")."""
    factor: int = 2
    """Each side is divided by this while coarse (2: a quarter of the pixels)."""
    min_side: int = 128
    """A view takes part only if its shorter side keeps at least this many pixels coarse."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.until <= 1.0:
            raise ConfigError(f"--coarse.until must be in [0, 1], got {self.until}")
        if self.factor < 1:
            raise ConfigError(f"--coarse.factor must be ≥ 1, got {self.factor}")
        if self.min_side < 1:
            raise ConfigError(f"--coarse.min-side must be ≥ 1, got {self.min_side}")


@dataclass(frozen=True)
class TrainConfig:
    """Train a dynamic Gaussian-splatting model on a scene."""

    data: str = "demo"
    """Dataset folder (D-NeRF/Blender, Panoptic, DyNeRF/N3DV or Nerfies/HyperNeRF; see
    `--format`), or `demo` for the built-in procedural scene."""
    output_dir: Path = Path("outputs")
    """Runs are written to OUTPUT_DIR/RUN_NAME."""
    run_name: str | None = None
    """Folder name of this run (default: method, dataset and start time)."""
    max_iters: int | None = None
    """Training iterations, warm-up included. None: sized from the data (more views and
    timestamps train longer; `training_steps` in dyngs/engine/capacity.py), and the run
    says how many."""
    time_budget: float | None = None
    """Minutes of training the whole schedule must fit in: `max_iters` (given, or sized) is
    re-planned from the measured step rate as the run goes, and each change is reported
    (dyngs/engine/budget.py). A re-plan changes the pace of the rest of the schedule, never
    moves it back. A budgeted run depends on the machine's speed."""
    warmup_iters: int = 200
    """Static warm-up: the canonical Gaussians alone are fitted for this many iterations."""
    warmup_time: float = 0.05
    """During the warm-up, train only on views with t ≤ this, so the canonical Gaussians are a
    sharp picture of the start of the sequence rather than a blur of all of it."""
    time_ramp: float = 0.3
    """Fraction of the run over which the training views' time window then widens from
    `warmup_time` to the whole sequence (0: all times at once). Motion is learned forward in
    time, following objects, instead of bridging large displacements in one go; the rest
    of the run then refines every time at once. 0.3 rather than half: with the
    deformation's rates sized to the run, a third of a run is enough to follow the motion,
    and the longer refinement gained the MuJoCo scenes on average; a window much faster
    than that loses the motion (docs/ACCURACY.md, "The time window: full at 30 % of the
    run")."""
    frontier_share: float = 0.5
    """While the window widens, this share of the steps trains on a view from its newest
    `frontier-span` of time, the rest on any view in it. Drawing from the whole window
    alone, a new time gets a share of the steps that shrinks as the window grows, and the
    deformation can fall behind the motion for good (docs/CAPACITY.md). 0 turns it off."""
    frontier_span: float = 0.1
    """Width in t of the newest part of the window that `frontier-share` draws from (the
    latest views when none is that recent)."""
    time_jitter: float = 0.0
    """Annealed smooth training (Deformable 3D Gaussians, Yang et al. 2024, who use 0.1):
    the model draws each training view at t + N(0, 1) · time-jitter · Δt · (1 − p), Δt the
    median spacing of the training times and p the run's progress, so that the
    deformation and the lifetimes are fitted around each time rather than at it alone.
    Off by default: 0.1 gained 3000-step runs on average but lost in ten-minute ones
    (docs/ACCURACY.md, "Annealed time jitter")."""
    batch_views: int = 1
    """Views per training step, the loss averaged over them. Under torchrun each process
    renders its share of them (docs/DISTRIBUTED.md), so P processes need at least P."""
    collective_timeout: float = 600.0
    """Several processes: seconds one waits for the others in a step before it stops the
    run with its last checkpoint (a dead process is noticed at once)."""
    seed: int = 0
    """Seeds every random choice (initialisation, view order, densification)."""
    device: str = "auto"
    """`auto` (CUDA when present), `cpu`, `cuda`, `cuda:1`, …"""
    dataset: Annotated[DataConfig, tyro.conf.OmitArgPrefixes] = dataclasses.field(
        default_factory=DataConfig
    )
    gaussians: GaussianConfig = dataclasses.field(default_factory=GaussianConfig)
    field: FieldConfig = dataclasses.field(default_factory=HexPlaneConfig)
    head: HeadConfig = dataclasses.field(default_factory=DeformationHeadConfig)
    renderer: RendererConfig = dataclasses.field(default_factory=CpuReferenceConfig)
    losses: LossConfig = dataclasses.field(default_factory=LossConfig)
    optim: OptimConfig = dataclasses.field(default_factory=OptimConfig)
    densify: DensifyConfig = dataclasses.field(default_factory=DensifyConfig)
    motion: MotionConfig = dataclasses.field(default_factory=MotionConfig)
    coarse: CoarseConfig = dataclasses.field(default_factory=CoarseConfig)
    max_bad_steps: int = 20
    """Stop when this many consecutive steps have a non-finite loss or gradient (such steps
    are skipped and counted; the last good checkpoint is kept)."""
    log_every: int = 25
    """Write scalars to TensorBoard every this many iterations."""
    image_every: int = 500
    """Write a rendered vs ground-truth image to TensorBoard every this many iterations."""
    checkpoint_every: int = 500
    """Save a checkpoint every this many iterations (and at the end, and on Ctrl-C)."""
    tensorboard: bool = True
    """Write TensorBoard event files into the run folder."""
    eval_split: str = "test"
    """Split evaluated at the end of training (metrics.json and images)."""
    method: tyro.conf.Suppress[str] = "custom"
    """Name of the preset this config came from (set by the CLI)."""
    pace: tyro.conf.Suppress[tuple[int, float, int] | None] = None
    """Set by `--time-budget` when it re-plans the step count: (step a, the schedule's
    position at a, the schedule's length). From step a on, the schedule (laid out for
    that length) runs from that position to its end over the steps left, so a re-plan
    changes its pace and never moves it backwards (`dyngs.engine.schedules.position`).
    None: the schedule's position is the step."""

    @property
    def steps(self) -> int:
        """`max_iters` once the config is sized for its data (`resolve_capacity`)."""
        if self.max_iters is None:
            raise ConfigError("this config's step count is not sized yet (resolve_capacity)")
        return self.max_iters

    def __post_init__(self) -> None:
        if self.max_iters is not None and self.max_iters < 0:
            raise ConfigError(f"--max-iters must be ≥ 0, got {self.max_iters}")
        if self.time_budget is not None and not self.time_budget > 0:
            raise ConfigError(f"--time-budget must be positive minutes, got {self.time_budget}")
        if self.warmup_iters < 0:
            raise ConfigError(f"--warmup-iters must be ≥ 0, got {self.warmup_iters}")
        if not 0.0 <= self.warmup_time <= 1.0:
            raise ConfigError(f"--warmup-time must be in [0, 1], got {self.warmup_time}")
        if not 0.0 <= self.time_ramp <= 1.0:
            raise ConfigError(f"--time-ramp must be in [0, 1], got {self.time_ramp}")
        if not 0.0 <= self.frontier_share <= 1.0:
            raise ConfigError(f"--frontier-share must be in [0, 1], got {self.frontier_share}")
        if not 0.0 < self.frontier_span <= 1.0:
            raise ConfigError(f"--frontier-span must be in (0, 1], got {self.frontier_span}")
        if not self.time_jitter >= 0.0:
            raise ConfigError(f"--time-jitter must be ≥ 0, got {self.time_jitter}")
        if self.batch_views < 1:
            raise ConfigError(f"--batch-views must be ≥ 1, got {self.batch_views}")
        if not self.collective_timeout > 0:
            raise ConfigError(
                f"--collective-timeout must be positive seconds, got {self.collective_timeout}"
            )
        if self.max_bad_steps < 1:
            raise ConfigError(f"--max-bad-steps must be ≥ 1, got {self.max_bad_steps}")
        if self.eval_split not in ("train", "val", "test"):
            raise ConfigError(f"--eval-split must be train, val or test, got {self.eval_split!r}")


__all__ = [
    "CoarseConfig",
    "FieldConfig",
    "HeadConfig",
    "LossConfig",
    "RendererConfig",
    "TrainConfig",
]

"""Static/dynamic separation: only the Gaussians that move pay for the deformation field.

Every Gaussian is static (drawn from its canonical parameters, never querying the field) or
dynamic (deformed by head(field(μ, t))). The split comes from the data, twice over:

- **Pixel evidence** (captures with fixed cameras: Panoptic, DyNeRF): a camera that stays
  put while time passes sees motion directly, as pixels that differ from their temporal
  median. At the end of the static warm-up, a Gaussian starts dynamic only if most of
  the fixed cameras that see it see its pixel change (a majority, so that a wall seen
  once behind a moving arm stays static); while the time window widens, revisits only
  promote, and every revisit keeps what the pixels see move dynamic. Monocular and
  moving-camera captures carry no such evidence: every Gaussian starts dynamic.
- **Measured motion** (every capture): once the training views span the whole sequence,
  and every `every` iterations after that, each Gaussian's deformation is evaluated at
  sampled training times. A dynamic Gaussian whose every point moves less than
  `static_pixels` pixels (at the scene centre) and whose opacity changes less than
  `static_opacity` becomes static, with its mean deformation baked into its canonical
  parameters, so that it is drawn where it was. A static Gaussian becomes dynamic again
  when the field where it sits moves (its neighbours move), or when its gradient keeps
  asking for a velocity (its region keeps an error that changes with time, which no static
  Gaussian can fix; see `DensifyState.pull`).

A scene where nothing is left dynamic trains and renders without the field at all.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from dyngs.datamanagers.base import Split
from dyngs.datamanagers.fixed_cameras import PIXEL_CHANGE, FixedCameras, dilate
from dyngs.errors import ConfigError
from dyngs.geometry import normalize_quaternion
from dyngs.model import DynamicGaussians
from dyngs.types import Camera

CHUNK = 65_536
"""Gaussians deformed at once when measuring motion (bounds the field's activations)."""


@dataclass(frozen=True)
class MotionConfig:
    """Static/dynamic separation (see `dyngs.engine.motion`)."""

    separate: bool = True
    """Decide per Gaussian whether it moves; False deforms every Gaussian at every step."""
    every: int = 500
    """Iterations between revisits of the split, once training spans the whole sequence."""
    samples: int = 16
    """Training times at which each Gaussian's motion is measured."""
    static_pixels: float = 0.5
    """A Gaussian whose points all move less than this many pixels at the scene centre is
    static: motion below half a pixel moves no edge across a pixel centre."""
    static_opacity: float = 0.02
    """… and whose opacity changes by less than this (about 5/255 of a fully covered pixel)."""
    pull_coherence: float = 0.5
    """A static Gaussian whose screen-space gradient is high enough to densify for becomes
    dynamic when its gradient also asks for a velocity this consistently (|Σ g (t - ½)| /
    Σ |g (t - ½)| over the views since the last refinement): an error that changes with
    time, which no static Gaussian can fix. Under-fitting in a still region pulls the same
    way at every time and scores about 1/√views."""
    pixel_change: float = PIXEL_CHANGE
    """Fixed cameras: a pixel whose early frames differ from its temporal median by more
    than this (largest channel, colours in [0, 1]) sees something that moves away; 0.1 ≈
    25/255 sits well above sensor and compression noise (a few /255 in DyNeRF's still
    regions) and below the contrast of a moving object against what is behind it."""
    start_from_pixels: bool = True
    """Fixed cameras, from initial points known to lie on surfaces (made from the images,
    or a cloud judged real): at the end of the warm-up, start only the Gaussians that most
    of the fixed cameras that see them see change dynamic (the rest static), and until the
    window is full revisit every `every` steps to promote (never demote) what its pixels,
    its field or its gradient say moves. False keeps every Gaussian dynamic until the first
    full revisit, once the window spans the sequence: on a real capture that was half a
    budgeted run's time, most of it spent deforming a still background, and the MuJoCo
    scenes trained 0.4 dB worse on the mean (docs/ACCURACY.md, "Fixed cameras start from
    their pixels")."""
    crop_field: bool = True
    """At the end of training, cut the field's planes to the span of the dynamic Gaussians
    (the only ones that query it): same features where they sit, no storage elsewhere."""
    start_crop: float | None = 0.005
    """When a synchronised capture's split (two or more views of each time) starts from
    the pixels (`start_from_pixels`), before the field has learned anything, cut its planes
    to the dynamic Gaussians between this quantile and its complement along each axis; the
    few beyond (a moving pixel's background, seen behind what moves) draw the field as
    still in time. The regularizers count their terms on the whole planes, so each kept
    cell is regularized as before, and a step no longer pays for the planes' empty room (on
    a real capture the field spans the room, the motion a corner of it). A sequence with
    one view of each time is left whole: its split grows from the pixels' quarter to
    nearly every Gaussian (the MuJoCo scenes'), so the start does not say where the field
    is needed. None keeps every field whole until the end."""

    def __post_init__(self) -> None:
        if self.every < 1 or self.samples < 2:
            raise ConfigError("--motion.every must be ≥ 1 and --motion.samples ≥ 2")
        if self.static_pixels < 0 or self.static_opacity < 0 or self.pixel_change < 0:
            raise ConfigError("--motion thresholds must be ≥ 0")
        if self.start_crop is not None and not 0 <= self.start_crop < 0.5:
            raise ConfigError(f"--motion.start-crop must be in [0, 0.5), got {self.start_crop}")


@dataclass
class Motion:
    """How far each Gaussian moves over the sampled times, and where it sits on average."""

    travel: Float[Tensor, " N"]
    """Largest displacement of any point of the Gaussian's 1σ ellipsoid from its mean pose,
    in world units (centre motion + size × (rotation angle + log-scale change))."""
    opacity_change: Float[Tensor, " N"]
    """Largest change of its opacity from its mean."""
    mean_deltas: dict[str, Tensor]
    """Its mean raw deltas, keyed like the canonical parameters (to bake into them)."""


def sample_times(times: Tensor, count: int) -> list[float]:
    """Up to `count` distinct training times, spread evenly through the sequence."""
    distinct = torch.unique(times.double().cpu())
    if len(distinct) <= count:
        return distinct.tolist()
    picks = torch.linspace(0, len(distinct) - 1, count).round().long()
    return distinct[picks].tolist()


@torch.no_grad()
def measure_motion(
    model: DynamicGaussians, times: list[float], index: Tensor | None = None
) -> Motion:
    """Deform the Gaussians in `index` (default: all) at `times` and measure their motion."""
    c = model.canonical
    device = c.means.device
    rows = torch.arange(len(c), device=device) if index is None else index
    travel = torch.zeros(len(rows), device=device)
    opacity_change = torch.zeros(len(rows), device=device)
    names = ("means", "quats", "log_scales", "opacity_logits", "sh_dc")
    mean_deltas = {n: torch.zeros_like(getattr(c, n)[rows]) for n in names}
    for start in range(0, len(rows), CHUNK):
        part = rows[start : start + CHUNK]
        raw = {n: getattr(c, n)[part] for n in names}
        stacked: dict[str, list[Tensor]] = {n: [] for n in names}
        for t in times:
            d, _ = model.deltas(t, part)
            stacked["means"].append(d.means)
            for name, delta in (
                ("quats", d.quats),
                ("log_scales", d.scales),
                ("opacity_logits", d.opacities),
                ("sh_dc", None if d.colors is None else d.colors[:, None, :]),
            ):
                stacked[name].append(torch.zeros_like(raw[name]) if delta is None else delta)
        deltas = {n: torch.stack(v) for n, v in stacked.items()}  # [T, M, ...]
        mean = {n: v.mean(0) for n, v in deltas.items()}
        size = (raw["log_scales"] + mean["log_scales"]).exp().amax(-1)
        centre = (deltas["means"] - mean["means"]).norm(dim=-1)
        q_now = normalize_quaternion(raw["quats"] + deltas["quats"])
        q_mean = normalize_quaternion(raw["quats"] + mean["quats"])
        cos_half = (q_now * q_mean).sum(-1).abs().clamp_max(1.0)
        angle = 2 * torch.acos(cos_half)
        rescale = (deltas["log_scales"] - mean["log_scales"]).abs().amax(-1)
        sl = slice(start, start + len(part))
        travel[sl] = (centre + size * (angle + rescale)).amax(0)
        opacity_now = torch.sigmoid(raw["opacity_logits"] + deltas["opacity_logits"])
        opacity_mean = torch.sigmoid(raw["opacity_logits"] + mean["opacity_logits"])
        opacity_change[sl] = (opacity_now - opacity_mean).abs().amax(0)
        for n in names:
            mean_deltas[n][sl] = mean[n]
    return Motion(travel, opacity_change, mean_deltas)


def is_static(motion: Motion, config: MotionConfig, pixel_size: float) -> Bool[Tensor, " N"]:
    return (motion.travel < config.static_pixels * pixel_size) & (
        motion.opacity_change < config.static_opacity
    )


@torch.no_grad()
def revisit(
    model: DynamicGaussians,
    config: MotionConfig,
    times: list[float],
    pixel_size: float,
    wants_motion: Tensor,
    pixels_move: Tensor | None = None,
    demote: bool = True,
) -> tuple[int, int]:
    """Revisit the split in place; returns (newly static, newly dynamic) counts.

    Dynamic Gaussians that no longer move are baked at their mean pose and made static,
    unless `pixels_move` marks them (fixed cameras see their pixels change). Static
    Gaussians where the field moves, that `wants_motion` marks (their region keeps an error
    that changes with time) or that `pixels_move` marks become dynamic, keeping their mean
    pose. `demote=False` only promotes (while the time window widens, a Gaussian that has
    not moved yet may still be about to).
    """
    c = model.canonical
    everyone = measure_motion(model, times)
    still = is_static(everyone, config, pixel_size)
    pixels = torch.zeros_like(still) if pixels_move is None else pixels_move.to(still.device)
    demoted = model.dynamic & still & ~pixels & demote
    promote = ~model.dynamic & (~still | wants_motion.to(still.device) | pixels)
    # Either way a Gaussian keeps its mean pose: a demoted one takes its mean deformation
    # into its canonical parameters, a promoted one gives the field's mean deformation back.
    for change, sign in ((demoted, 1.0), (promote, -1.0)):
        if bool(change.any()):
            rows = change.nonzero().squeeze(1)
            for name, delta in everyone.mean_deltas.items():
                getattr(c, name).index_add_(0, rows, delta[rows], alpha=sign)
    model.dynamic = (model.dynamic & ~demoted) | promote
    return int(demoted.sum()), int(promote.sum())


def pixel_motion_maps(
    split: Split, fixed: FixedCameras, early: float
) -> list[Float[Tensor, "H W"]]:
    """Per fixed camera, how far each pixel in the early frames (t ≤ `early`, or the
    earliest) is from what it shows most of the time (its temporal median), in [0, 1].

    The canonical Gaussians are fitted to those early frames: one that differs there from
    the pixel's usual content sits on something that later moves away, while background
    that a moving object only passes in front of matches its median and stays static.
    """
    maps = []
    for camera, order in enumerate(fixed.views):
        first = float(split.times[order[0]])
        reference = [i for i in order if float(split.times[i]) <= max(early, first)]
        start = torch.stack([split.images[i] for i in reference]).float().mean(0) / 255.0
        maps.append(fixed.distance(camera, start))
    return maps


@dataclass
class FixedCameraMotion:
    """What a capture's fixed cameras see move: per fixed camera, its camera and its
    `pixel_motion_maps` map, dilated by one pixel (a point on a moving edge may sit just
    beside the change). It depends on the images only, so a run computes it once and asks
    it of the Gaussians at every revisit."""

    cameras: list[Camera]
    maps: list[Float[Tensor, "H W"]]

    @classmethod
    def of(
        cls, split: Split, early: float = 0.0, fixed: FixedCameras | None = None
    ) -> FixedCameraMotion | None:
        """None when the split has no fixed cameras. `fixed`: the split's, when already read."""
        fixed = fixed or FixedCameras.of(split)
        if fixed is None:
            return None
        maps = [dilate(motion_map) for motion_map in pixel_motion_maps(split, fixed, early)]
        return cls(fixed.cameras, maps)

    @torch.no_grad()
    def evidence(self, means: Float[Tensor, "N 3"], config: MotionConfig) -> Bool[Tensor, " N"]:
        """Which Gaussians most of the fixed cameras that see them see move away."""
        votes = torch.zeros(len(means), device=means.device)
        seen = torch.zeros(len(means), device=means.device)
        for camera, motion_map in zip(self.cameras, self.maps, strict=True):
            w2c = camera.world_to_camera.to(means.device, means.dtype)
            p = means @ w2c[:3, :3].T + w2c[:3, 3]
            z = p[:, 2]
            front = z > camera.near
            zs = torch.where(front, z, 1.0)
            u = (camera.fx * p[:, 0] / zs + camera.cx).floor()
            v = (camera.fy * p[:, 1] / zs + camera.cy).floor()
            inside = front & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
            ui = u.clamp(0, camera.width - 1).long()
            vi = v.clamp(0, camera.height - 1).long()
            moving = motion_map.to(means.device)[vi, ui] > config.pixel_change
            votes += (inside & moving).to(votes.dtype)
            seen += inside.to(seen.dtype)
        # A Gaussian no fixed camera sees has no evidence either way: it stays dynamic.
        return (votes > 0.5 * seen) | (seen == 0)


def model_bytes(model: DynamicGaussians, sh_degree: int | None = None) -> int:
    """Bytes a stored model needs: the Gaussians' parameters (SH bands up to `sh_degree`,
    by default the active degree), τ and σ of the temporal ones (with a bit a Gaussian to
    say which) and, when any Gaussian is dynamic, the field and head."""
    c = model.canonical
    sh_degree = model.active_sh_degree if sh_degree is None else sh_degree
    size = c.means.element_size()
    floats = 3 + 4 + 3 + 1 + 3 * (sh_degree + 1) ** 2  # mean, quaternion, scale, opacity, SH
    flags = math.ceil(len(c) / 8)  # one bit a Gaussian
    total = len(c) * floats * size + flags  # + the dynamic flags
    temporal = int(c.temporal().sum())
    if temporal:
        total += temporal * 2 * size + flags  # τ, log σ; + the temporal flags
    if bool(model.dynamic.any()):
        total += sum(p.numel() * p.element_size() for p in model.field.parameters())
        total += sum(p.numel() * p.element_size() for p in model.head.parameters())
    return total

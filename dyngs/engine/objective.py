"""The training objective: the loss of one step as named, weighted terms.

- `photometric`: (1 − λ)·L1 + λ·D-SSIM against the view's image (Kerbl et al. 2023),
  weighted per pixel by the dataset's mask (`--losses.masked`) and by how far a fixed
  camera's pixel is from its usual content (`--losses.change-weight`);
- while the model deforms: the plane regularizers of K-Planes (total variation of the
  spatial planes, smoothness and L1-to-static of the time planes) and, with
  `--losses.arap`, local rigidity between this time and a random other one;
- extra terms an installed package registers in `LOSS_TERMS` (entry-point group
  `dyngs.losses`: a function of `TermInputs` returning a scalar), each switched on by
  `--losses.extra NAME WEIGHT`.

A term whose weight is 0 is not computed at all. The trainer sums the terms; tests and
TensorBoard read them by name.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from dyngs.config import LossConfig
from dyngs.datamanagers.datamanager import DataManager, TrainBatch, area_resize
from dyngs.errors import ConfigError
from dyngs.fields.base import PlaneGrids
from dyngs.losses import compiled_planes
from dyngs.losses.arap import arap_loss, neighbor_weights
from dyngs.losses.photometric import photometric
from dyngs.losses.temporal import time_l1_to_static, time_smoothness
from dyngs.losses.tv import plane_roughness, plane_tv
from dyngs.model import DynamicGaussians
from dyngs.neighbors import knn
from dyngs.registry import Registry
from dyngs.renderers.base import ABSENT_BELOW, RenderOutput
from dyngs.types import Gaussians


@dataclass
class TermInputs:
    """What an extra loss term may read about the step (H×W image, N Gaussians)."""

    out: RenderOutput
    batch: TrainBatch
    gaussians: Gaussians
    """The Gaussians drawn at the view's time."""
    model: DynamicGaussians
    step: int


LossTerm = Callable[[TermInputs], Float[Tensor, ""]]


def _check_term(item: object) -> str | None:
    return None if callable(item) else "is not callable"


LOSS_TERMS: Registry[LossTerm] = Registry("loss term", "dyngs.losses", _check_term)


def plane_terms(weights: LossConfig, planes: PlaneGrids) -> dict[str, Tensor]:
    """Plane regularizers (K-Planes, Fridovich-Keil et al. 2023), weighted; a term with
    weight 0, or a field without planes, costs nothing. On the CPU, for a field that gives
    its stacked plane groups, the default three (TV, time smoothness, time L1) are one
    compiled pass each way (`compiled_planes`): these PyTorch functions' values to float
    rounding."""
    stacked = planes.spatial_groups + planes.temporal_groups
    if weights.plane_roughness == 0 and compiled_planes.usable(stacked):
        return _compiled_plane_terms(weights, planes)
    terms: dict[str, Tensor] = {}
    if weights.plane_tv > 0 and planes.spatial:
        terms["plane_tv"] = weights.plane_tv * plane_tv(planes.spatial, planes.spatial_whole)
    if weights.plane_roughness > 0 and planes.spatial:
        terms["plane_roughness"] = weights.plane_roughness * plane_roughness(planes.spatial)
    if weights.time_smoothness > 0 and planes.temporal:
        smoothness = time_smoothness(planes.temporal, planes.temporal_whole)
        terms["time_smoothness"] = weights.time_smoothness * smoothness
    if weights.time_l1 > 0 and planes.temporal:
        pull = time_l1_to_static(planes.temporal, planes.temporal_whole)
        terms["time_l1"] = weights.time_l1 * pull
    return terms


def _compiled_plane_terms(weights: LossConfig, planes: PlaneGrids) -> dict[str, Tensor]:
    """`plane_terms` without roughness, through `compiled_planes.plane_values` on the
    field's stacked plane groups."""
    spatial = planes.spatial_groups if weights.plane_tv > 0 else []
    timed = weights.time_smoothness > 0 or weights.time_l1 > 0
    temporal = planes.temporal_groups if timed else []
    if not spatial and not temporal:
        return {}
    whole = (
        planes.spatial_groups_whole if spatial else None,
        planes.temporal_groups_whole if temporal else None,
    )
    tv, smoothness, l1 = compiled_planes.plane_values(spatial, temporal, *whole)
    terms: dict[str, Tensor] = {}
    if spatial:
        terms["plane_tv"] = weights.plane_tv * tv
    if weights.time_smoothness > 0 and temporal:
        terms["time_smoothness"] = weights.time_smoothness * smoothness
    if weights.time_l1 > 0 and temporal:
        terms["time_l1"] = weights.time_l1 * l1
    return terms


class Objective:
    """The loss terms of a step (see the module docstring), with the little state they
    keep: the rigidity term's neighbourhoods, recomputed after any topology change."""

    def __init__(
        self,
        config: LossConfig,
        data: DataManager,
        pixel_change: float,
        generator: torch.Generator,
    ) -> None:
        self.config = config
        self.data = data
        self.pixel_change = pixel_change
        self.generator = generator
        self.extra = {name: LOSS_TERMS.get(name) for name in config.extra}
        self._neighbors: tuple[Tensor, Tensor] | None = None

    def pixel_weights(self, batch: TrainBatch) -> Float[Tensor, "H W 1"] | None:
        """Per-pixel weights of the photometric loss: the dataset's mask with
        `--losses.masked`, times 1 + `--losses.change-weight` where a fixed camera sees a
        pixel differ from its usual content. A coarse view (`TrainBatch.coarse`) takes the
        whole view's weights, area-averaged as its image was."""
        mask = batch.mask if self.config.masked else None
        fixed = self.data.fixed_cameras if self.config.change_weight > 0 else None
        if fixed is None:
            return mask
        whole = batch.full or batch  # what a fixed camera's temporal median is compared with
        changed = fixed.changed(whole.index, whole.image, self.pixel_change)
        if changed is None:
            return mask
        weights = (1 + self.config.change_weight * changed.to(batch.image.dtype))[..., None]
        if batch.full is not None:
            weights = area_resize(weights, batch.camera)
        return weights if mask is None else weights * mask

    def change_weight_note(self) -> str:
        """What `--losses.change-weight` does on this capture, for the log."""
        weight, fixed = self.config.change_weight, self.data.fixed_cameras
        if fixed is None:
            return (
                f"warning: --losses.change-weight {weight:g} has no effect: no camera of "
                f"{self.data.scene.name} stays put at three or more times"
            )
        return (
            f"[loss] {len(fixed.views)} fixed cameras: pixels that differ from "
            f"their camera's temporal median count {1 + weight:g}× in the photometric loss"
        )

    def terms(
        self,
        model: DynamicGaussians,
        out: RenderOutput,
        batch: TrainBatch,
        gaussians: Gaussians,
        step: int,
        other_time: float | None = None,
    ) -> dict[str, Tensor]:
        """The weighted terms of this view's loss, by name. `other_time`: the rigidity
        term's random other time, when drawn beforehand (`other_times`)."""
        cfg = self.config
        weights = self.pixel_weights(batch)
        terms = {"photometric": photometric(out.rgb, batch.image, cfg.dssim, weights)}
        if model.deforms:
            terms |= plane_terms(cfg, model.field.planes())
            if cfg.arap > 0:
                terms["arap"] = cfg.arap * self.rigidity(model, gaussians.means, other_time)
        for name, term in self.extra.items():
            value = term(TermInputs(out, batch, gaussians, model, step))
            if value.ndim != 0:
                raise ConfigError(f"loss term {name!r} returned shape {tuple(value.shape)}")
            terms[name] = cfg.extra[name] * value
        return terms

    @property
    def absent_below(self) -> float:
        """The presence under which a step may leave a Gaussian undeformed
        (`DynamicGaussians.at`): the renderers' α floor when only the drawn image is read,
        0 (deform all) when a term reads the Gaussians themselves (the rigidity term, and
        any plugin term, which is handed them)."""
        return 0.0 if self.config.arap > 0 or self.extra else ABSENT_BELOW

    def other_times(self, model: DynamicGaussians, views: int) -> list[float | None]:
        """The rigidity term's random other time for each of a step's `views` views, drawn
        in view order (None when the term is off). Every process draws them all, so that
        the shared generator stays the same on every rank whichever views it renders."""
        if not (model.deforms and self.config.arap > 0):
            return [None] * views
        return [float(torch.rand((), generator=self.generator)) for _ in range(views)]

    def rigidity(
        self, model: DynamicGaussians, means_now: Tensor, other: float | None = None
    ) -> Tensor:
        """Neighbour distances of `means_now` against those at the time `other` (random
        when not given) (ARAP)."""
        if self._neighbors is None:
            with torch.no_grad():
                canonical = model.canonical.means.detach()
                neighbors = knn(canonical, self.config.arap_neighbors)
                d = (canonical[:, None] - canonical[neighbors]).norm(dim=-1)
                weights = neighbor_weights(canonical, neighbors, float(d.mean()) + 1e-12)
            self._neighbors = (neighbors, weights)
        neighbors, weights = self._neighbors
        if other is None:
            other = float(torch.rand((), generator=self.generator))
        with torch.no_grad():
            means_other = model.at(other, sh_degree=0, deform=True).means
        return arap_loss(means_now, means_other, neighbors, weights)

    def on_topology(self) -> None:
        """The Gaussians changed: neighbourhoods are recomputed on the new set."""
        self._neighbors = None

"""Mip-Splatting's 3D filter (Yu et al. 2024): how finely the training views sample each
Gaussian, and the filter set from that. The filter itself is the model's
(`dyngs.model.smooth_3d`, `DynamicGaussians.set_filter`); this module measures what it
is sized by. The lifecycle sets it on the initial Gaussians and refreshes it every
`--densify.refine-every` steps (`schedules.is_filter_step`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from dyngs.engine.distributed import SINGLE, ProcessGroup
from dyngs.model import DynamicGaussians
from dyngs.types import Camera

FRUSTUM_MARGIN = 0.15
"""A Gaussian counts as seen by a view when its centre projects within this fraction of
the image's size beyond its edges (Mip-Splatting's margin, Yu et al. 2024)."""


PRESENT = 0.05
"""A temporal Gaussian counts for a view when its temporal presence (the factor on its
opacity) at the view's time exceeds this. The rule reads when a Gaussian exists, not
its learned opacity: an opacity reset lowers every opacity at once, and the filter
scales the drawn opacity down itself, so a rule on opacity fed back into the filter
(texture lost about 1 dB a seed with one, docs/ACCURACY.md)."""


def sampling_rates(
    means: Float[Tensor, "N 3"], present: Bool[Tensor, " N"], camera: Camera
) -> Float[Tensor, " N"]:
    """How finely the camera samples space at each present Gaussian: focal length ÷
    depth, in pixels per world unit (the larger focal length, should pixels not be
    square); 0 for a Gaussian behind the near plane, outside the frustum (with
    `FRUSTUM_MARGIN`) or not present. Mip-Splatting's ν (Yu et al. 2024)."""
    w2c = camera.world_to_camera.to(means)
    local = means @ w2c[:3, :3].T + w2c[:3, 3]
    depth = local[:, 2]
    safe = torch.where(depth > camera.near, depth, 1.0)
    x = camera.fx * local[:, 0] / safe + camera.cx
    y = camera.fy * local[:, 1] / safe + camera.cy
    mx, my = FRUSTUM_MARGIN * camera.width, FRUSTUM_MARGIN * camera.height
    seen = (depth > camera.near) & present
    seen &= (x >= -mx) & (x <= camera.width + mx) & (y >= -my) & (y <= camera.height + my)
    return torch.where(seen, max(camera.fx, camera.fy) / safe, 0.0)


@torch.no_grad()
def finest_sampling_rates(
    model: DynamicGaussians, poses: Sequence[tuple[Camera, float]]
) -> Float[Tensor, " N"]:
    """Each Gaussian's finest `sampling_rates` over the poses' views, the model as it draws
    at each pose's time (deformed when it deforms; present there by `PRESENT`). Poses in
    time order run one deformation a time."""
    canonical = model.canonical
    rates = torch.zeros(len(canonical), device=canonical.means.device)
    drawn: tuple[float, Tensor, Tensor] | None = None
    for camera, t in poses:
        if drawn is None or drawn[0] != t:
            means = model.raw_at(t)["means"]
            present = torch.ones(len(means), dtype=torch.bool, device=means.device)
            if bool(canonical.temporal().any()):
                present = canonical.temporal_factor(t) > PRESENT
            drawn = (t, means, present)
        rate = sampling_rates(drawn[1], drawn[2], camera).to(rates.dtype)
        torch.maximum(rates, rate, out=rates)
    return rates


def refresh_filter(
    model: DynamicGaussians,
    poses: Sequence[tuple[Camera, float]],
    strength: float,
    group: ProcessGroup = SINGLE,
) -> float:
    """Set the model's 3D filter (`DynamicGaussians.set_filter`) from the finest sampling
    rate of the poses' views, as Mip-Splatting does over all of its training cameras;
    under several processes, each passes its share of the views and the maxima are
    exchanged. Returns the seconds it took."""
    started = time.perf_counter()
    rates = finest_sampling_rates(model, poses)
    group.max_([rates])
    model.set_filter(rates, strength)
    return time.perf_counter() - started

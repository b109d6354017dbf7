"""Losses and regularizers: pure functions of tensors that return a scalar tensor."""

from dyngs.losses.arap import arap_loss, neighbor_weights, safe_norm
from dyngs.losses.photometric import dssim, l1, photometric, ssim_map
from dyngs.losses.temporal import time_l1_to_static, time_smoothness
from dyngs.losses.tv import plane_roughness, plane_tv

__all__ = [
    "arap_loss",
    "dssim",
    "l1",
    "neighbor_weights",
    "photometric",
    "plane_roughness",
    "plane_tv",
    "safe_norm",
    "ssim_map",
    "time_l1_to_static",
    "time_smoothness",
]

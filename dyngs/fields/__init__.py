"""Spatiotemporal feature fields (HexPlane, MLP) and the deformation head."""

from dyngs.fields.base import Field, PlaneGrids
from dyngs.fields.heads import DeformationHead, DeformationHeadConfig, Deltas
from dyngs.fields.hexplane import HexPlaneConfig, HexPlaneField
from dyngs.fields.mlp import MLPField, MLPFieldConfig

__all__ = [
    "DeformationHead",
    "DeformationHeadConfig",
    "Deltas",
    "Field",
    "HexPlaneConfig",
    "HexPlaneField",
    "MLPField",
    "MLPFieldConfig",
    "PlaneGrids",
]

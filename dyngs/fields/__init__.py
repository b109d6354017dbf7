"""Spatiotemporal feature fields (HexPlane, MLP) and the deformation head.

`FIELDS` and `HEADS` hold their configs by name (`field:hexplane`, `field:mlp`); an
installed package adds its own through the `dyngs.fields` and `dyngs.heads` entry-point
groups (see `dyngs.registry`).
"""

from dyngs.fields.base import Croppable, Field, FieldSpec, Head, HeadSpec, PlaneGrids
from dyngs.fields.heads import DeformationHead, DeformationHeadConfig, Deltas
from dyngs.fields.hexplane import HexPlaneConfig, HexPlaneField
from dyngs.fields.mlp import MLPField, MLPFieldConfig
from dyngs.registry import Registry, is_config_class

FIELDS: Registry[type[FieldSpec]] = Registry("field", "dyngs.fields", is_config_class)
FIELDS.register("hexplane", HexPlaneConfig)
FIELDS.register("mlp", MLPFieldConfig)

HEADS: Registry[type[HeadSpec]] = Registry("deformation head", "dyngs.heads", is_config_class)
HEADS.register("mlp", DeformationHeadConfig)

__all__ = [
    "FIELDS",
    "HEADS",
    "Croppable",
    "DeformationHead",
    "DeformationHeadConfig",
    "Deltas",
    "Field",
    "FieldSpec",
    "Head",
    "HeadSpec",
    "HexPlaneConfig",
    "HexPlaneField",
    "MLPField",
    "MLPFieldConfig",
    "PlaneGrids",
]

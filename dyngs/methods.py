"""Method presets: named, complete training configs offered as `dyngs-train` subcommands.

`METHODS` holds them by name; an installed package adds its own through the
`dyngs.methods` entry-point group, each entry point naming a `TrainConfig` or a
zero-argument callable returning one:

    [project.entry-points."dyngs.methods"]
    my-method = "my_package.presets:my_method"

A preset only chooses among components; to add a component itself (a field, a renderer,
a dataset format) register it in its own group (see `dyngs.registry`).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable

from dyngs.config import TrainConfig
from dyngs.fields.mlp import MLPFieldConfig
from dyngs.registry import Registry
from dyngs.renderers import default_renderer

Preset = TrainConfig | Callable[[], TrainConfig]


def _check(item: object) -> str | None:
    return None if isinstance(item, TrainConfig) or callable(item) else "is not a TrainConfig"


METHODS: Registry[Preset] = Registry("method preset", "dyngs.methods", _check)


def _hexplane_4dgs() -> TrainConfig:
    """4D Gaussian Splatting (Wu et al. 2024): a multi-resolution HexPlane and an MLP head."""
    return TrainConfig(renderer=default_renderer())


def _mlp_4dgs() -> TrainConfig:
    """Deformable 3D Gaussians (Yang et al. 2024): a positional-encoding MLP field."""
    return TrainConfig(field=MLPFieldConfig(), renderer=default_renderer())


METHODS.register("hexplane-4dgs", _hexplane_4dgs)
METHODS.register("mlp-4dgs", _mlp_4dgs)


def method_presets() -> tuple[dict[str, TrainConfig], dict[str, str]]:
    """Every preset (built-in, then third-party) and a one-line description of each."""
    presets: dict[str, TrainConfig] = {}
    descriptions: dict[str, str] = {}
    for entry in METHODS:
        try:
            item = entry.item
            config = item if isinstance(item, TrainConfig) else item()
        except Exception as error:  # a broken plugin must not break dyngs-train
            warnings.warn(
                f"method preset {entry.name!r} ({entry.origin}) failed to load: {error}",
                stacklevel=2,
            )
            continue
        if not isinstance(config, TrainConfig):
            warnings.warn(
                f"method preset {entry.name!r} ({entry.origin}) is not a TrainConfig; ignored",
                stacklevel=2,
            )
            continue
        presets[entry.name] = dataclasses.replace(config, method=entry.name)
        plugin = entry.origin != "dyngs"
        descriptions[entry.name] = f"{entry.origin} (plugin)" if plugin else entry.description
    return presets, descriptions

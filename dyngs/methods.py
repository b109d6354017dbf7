"""Method presets: named, complete training configs offered as `dyngs-train` subcommands.

Third-party packages add presets through the `dyngs.methods` entry-point group; each
entry point names a `TrainConfig` or a zero-argument callable returning one:

    [project.entry-points."dyngs.methods"]
    my-method = "my_package.presets:my_method"
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from importlib.metadata import entry_points

from dyngs.config import TrainConfig
from dyngs.fields.mlp import MLPFieldConfig
from dyngs.renderers import default_renderer

ENTRY_POINT_GROUP = "dyngs.methods"


def _hexplane_4dgs() -> TrainConfig:
    """4D Gaussian Splatting (Wu et al. 2024): a multi-resolution HexPlane and an MLP head."""
    return TrainConfig(renderer=default_renderer())


def _mlp_4dgs() -> TrainConfig:
    """Deformable 3D Gaussians (Yang et al. 2024): a positional-encoding MLP field."""
    return TrainConfig(field=MLPFieldConfig(), renderer=default_renderer())


BUILTIN: dict[str, Callable[[], TrainConfig]] = {
    "hexplane-4dgs": _hexplane_4dgs,
    "mlp-4dgs": _mlp_4dgs,
}


def method_presets() -> tuple[dict[str, TrainConfig], dict[str, str]]:
    """Every preset (built-in, then third-party) and a one-line description of each."""
    presets: dict[str, TrainConfig] = {}
    descriptions: dict[str, str] = {}
    for name, make in BUILTIN.items():
        presets[name] = dataclasses.replace(make(), method=name)
        descriptions[name] = (make.__doc__ or name).strip().splitlines()[0]
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name in presets:
            warnings.warn(
                f"method preset {ep.name!r} from {ep.value} shadows an existing one; ignored",
                stacklevel=2,
            )
            continue
        try:
            obj = ep.load()
            config = obj() if callable(obj) and not isinstance(obj, TrainConfig) else obj
        except Exception as error:  # a broken plugin must not break dyngs-train
            warnings.warn(
                f"method preset {ep.name!r} ({ep.value}) failed to load: {error}", stacklevel=2
            )
            continue
        if not isinstance(config, TrainConfig):
            warnings.warn(
                f"method preset {ep.name!r} ({ep.value}) is not a TrainConfig; ignored",
                stacklevel=2,
            )
            continue
        presets[ep.name] = dataclasses.replace(config, method=ep.name)
        descriptions[ep.name] = f"{ep.value} (plugin)"
    return presets, descriptions

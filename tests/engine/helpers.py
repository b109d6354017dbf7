"""Small trainers on the built-in scene for engine tests."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch
from torch import nn

from dyngs.config import TrainConfig
from dyngs.datamanagers.datamanager import DataConfig
from dyngs.datamanagers.procedural import ProceduralSceneConfig, demo_path
from dyngs.engine.trainer import Trainer
from dyngs.engine.writer import NullWriter
from dyngs.fields.heads import DeformationHead
from dyngs.fields.hexplane import HexPlaneConfig

# A small scene and a small field keep each step at a few milliseconds.
TINY_SCENE = ProceduralSceneConfig(
    resolution=32, num_times=6, views_per_time=2, num_test=3, num_val=2
)


def tiny_config(**overrides: Any) -> TrainConfig:
    config = TrainConfig(
        data=str(demo_path(TINY_SCENE)),
        max_iters=20,
        warmup_iters=2,
        tensorboard=False,
        field=HexPlaneConfig(resolution=(8, 8, 8, 4), multires=(1,), features=8),
        dataset=DataConfig(num_random_points=500),
    )
    return dataclasses.replace(config, **overrides)


def tiny_trainer(tmp_path: Path, **overrides: Any) -> Trainer:
    return Trainer(tiny_config(**overrides), tmp_path, NullWriter())


def output_layer(head: object, branch: str) -> nn.Linear | None:
    """The last Linear of the built-in deformation head's branch `branch` (None when that
    attribute is not deformed): its bias is a constant delta."""
    assert isinstance(head, DeformationHead)
    layers = getattr(head, branch)
    if layers is None:
        return None
    assert isinstance(layers, nn.Sequential) and isinstance(layers[-1], nn.Linear)
    return layers[-1]


def gradients_reaching(module: nn.Module) -> tuple[set[str], set[str]]:
    """(every parameter's name, the set that fills with the names of those that get a
    non-zero gradient in later backward passes; a hook on each parameter records it)."""
    named = dict(module.named_parameters())
    reached: set[str] = set()
    for name, param in named.items():
        param.register_hook(
            lambda g, name=name: reached.add(name) if bool(g.abs().sum() > 0) else None
        )
    return set(named), reached


def field_calls(field: object) -> list[int]:
    """How many points each later call of `field` is given (a forward hook appends them)."""
    assert isinstance(field, nn.Module)
    calls: list[int] = []
    field.register_forward_hook(lambda module, args, out: calls.append(args[0].shape[0]))
    return calls


def assert_same_state(a: dict[str, Any], b: dict[str, Any], context: str = "") -> None:
    """Two state_dicts hold the same keys and, bit for bit, the same values (tensors
    compared with torch.equal, the model's extra state with ==)."""
    assert a.keys() == b.keys(), context
    for key, value in a.items():
        same = torch.equal(value, b[key]) if isinstance(value, torch.Tensor) else value == b[key]
        assert same, f"{key} differs {context}".strip()

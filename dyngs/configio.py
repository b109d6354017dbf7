"""Resolved configs as JSON, so a run folder alone is enough to resume or evaluate it.

Every dataclass is written with its class path (needed to tell the members of a tagged
union apart); reading converts lists back to tuples and strings back to paths following
the dataclass's type hints.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import types
import typing
from pathlib import Path
from typing import Any

from dyngs.errors import ConfigError
from dyngs.io import atomic_write_text

CLASS_KEY = "__class__"


def config_to_dict(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        out: dict[str, Any] = {CLASS_KEY: f"{type(obj).__module__}:{type(obj).__qualname__}"}
        for f in dataclasses.fields(obj):
            out[f.name] = config_to_dict(getattr(obj, f.name))
        return out
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (tuple, list)):
        return [config_to_dict(x) for x in obj]
    if isinstance(obj, dict):
        return {k: config_to_dict(v) for k, v in obj.items()}
    return obj


def _import_class(path: str) -> type:
    module, _, name = path.partition(":")
    cls: Any = importlib.import_module(module)
    for part in name.split("."):
        cls = getattr(cls, part)
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise ValueError(f"{path} is not a config dataclass")
    return cls


def _coerce(hint: Any, value: Any) -> Any:
    """Bring a JSON value back to the type a dataclass field declares."""
    if value is None:
        return None
    if isinstance(value, dict) and CLASS_KEY in value:
        return config_from_dict(value)
    origin = typing.get_origin(hint)
    if origin is typing.Annotated:
        return _coerce(typing.get_args(hint)[0], value)
    if origin in (typing.Union, types.UnionType):
        for arg in typing.get_args(hint):
            if arg is type(None):
                continue
            if arg is Path and isinstance(value, str):
                return Path(value)
            if typing.get_origin(arg) is tuple and isinstance(value, list):
                return _coerce(arg, value)
        return value
    if hint is Path:
        return Path(value)
    if origin is tuple and isinstance(value, list):
        args = typing.get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(args[0], v) for v in value)
        return tuple(_coerce(a, v) for a, v in zip(args, value, strict=False))
    return value


def config_from_dict(data: dict[str, Any]) -> Any:
    cls = _import_class(data[CLASS_KEY])
    hints = typing.get_type_hints(cls, include_extras=True)
    kwargs = {
        f.name: _coerce(hints[f.name], data[f.name])
        for f in dataclasses.fields(cls)
        if f.name in data and f.init
    }
    return cls(**kwargs)


def save_config(path: Path, config: Any) -> None:
    atomic_write_text(path, json.dumps(config_to_dict(config), indent=2) + "\n")


def load_config(path: Path) -> Any:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no config here (is this a dyngs run folder?)") from None
    except json.JSONDecodeError as error:
        raise ConfigError(
            f"{path}: malformed JSON at line {error.lineno}, column {error.colno}"
        ) from None
    return config_from_dict(data)

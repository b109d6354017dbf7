"""Registries: every swappable part of dyngs is chosen by name.

A registry maps names to components of one kind: field configs, deformation-head configs,
renderer configs, dataset formats, extra loss terms, method presets. dyngs registers its
own at import; an installed package adds more through an entry-point group, read
whenever a registry is asked for its names (each entry point is loaded once):

    [project.entry-points."dyngs.fields"]
    my-field = "my_package.fields:MyFieldConfig"

`--field` then offers `field:my-field` beside the built-in ones, because the command
line's tagged unions are generated from the registries (`tyro_union`) when `dyngs.config`
is imported. A plugin that
fails to import, or gives something of the wrong kind, is skipped with one warning:
a broken plugin must not break dyngs. A plugin module must not import `dyngs.config`
at import time (that module builds its unions from the registries).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Annotated, Any, Generic, TypeVar, Union

import tyro

from dyngs.errors import ConfigError

T = TypeVar("T")


@dataclass(frozen=True)
class Entry(Generic[T]):
    name: str
    item: T
    description: str
    origin: str
    """`dyngs` for a built-in entry, else the entry point's `module:attribute`."""


class Registry(Generic[T]):
    """Named components of one kind, built-in and from the entry-point group `group`.

    `check(item)` returns None for an acceptable item and otherwise says what is wrong
    with it; plugins that fail it are skipped with a warning.
    """

    def __init__(
        self, kind: str, group: str, check: Callable[[object], str | None] | None = None
    ) -> None:
        self.kind = kind
        self.group = group
        self._check = check
        self._entries: dict[str, Entry[T]] = {}
        self._seen: set[tuple[str, str]] = set()

    def register(self, name: str, item: T, description: str | None = None) -> T:
        """Add a built-in entry (or a plugin's, when it registers itself); returns `item`."""
        if name in self._entries:
            raise ValueError(f"{self.kind} {name!r} is already registered")
        self._entries[name] = Entry(name, item, description or _first_line(item), "dyngs")
        return item

    def load_plugins(self) -> None:
        """Load the entry points of the group that were not seen before."""
        for ep in entry_points(group=self.group):
            if (ep.name, ep.value) in self._seen:
                continue
            self._seen.add((ep.name, ep.value))
            if ep.name in self._entries:
                warnings.warn(
                    f"{self.kind} {ep.name!r} from {ep.value} shadows an existing one; ignored",
                    stacklevel=2,
                )
                continue
            try:
                item = ep.load()
            except Exception as error:  # a broken plugin must not break dyngs
                warnings.warn(
                    f"{self.kind} {ep.name!r} ({ep.value}) failed to load: {error}", stacklevel=2
                )
                continue
            problem = self._check(item) if self._check is not None else None
            if problem is not None:
                warnings.warn(
                    f"{self.kind} {ep.name!r} ({ep.value}) {problem}; ignored", stacklevel=2
                )
                continue
            self._entries[ep.name] = Entry(ep.name, item, _first_line(item), ep.value)

    def entries(self) -> list[Entry[T]]:
        self.load_plugins()
        return list(self._entries.values())

    def names(self) -> list[str]:
        return [entry.name for entry in self.entries()]

    def __iter__(self) -> Iterator[Entry[T]]:
        return iter(self.entries())

    def __contains__(self, name: object) -> bool:
        return name in self.names()

    def get(self, name: str) -> T:
        """The entry named `name`; a one-line ConfigError listing the known names if none."""
        self.load_plugins()
        entry = self._entries.get(name)
        if entry is None:
            known = ", ".join(self.names())
            raise ConfigError(f"unknown {self.kind} {name!r}: known are {known}")
        return entry.item

    def name_of(self, item: object) -> str:
        """The name `item` (or, for an instance, its class) is registered under."""
        self.load_plugins()
        for entry in self._entries.values():
            if entry.item is item or entry.item is type(item):
                return entry.name
        raise ConfigError(f"{type(item).__qualname__} is not a registered {self.kind}")


def tyro_union(registry: Registry[type[Any]]) -> Any:
    """The tagged union the command line offers for a registry of config classes:
    `kind:NAME` chooses the config registered as NAME."""
    members = tuple(
        Annotated[entry.item, tyro.conf.subcommand(entry.name, description=entry.description)]
        for entry in registry.entries()
    )
    return Union[members]  # noqa: UP007 (tyro reads the tags from this form)


def is_config_class(item: object) -> str | None:
    """`check` for registries of configs: a dataclass with a `build` method."""
    if not (isinstance(item, type) and dataclasses.is_dataclass(item)):
        return "is not a dataclass"
    if not callable(getattr(item, "build", None)):
        return "has no build() method"
    return None


def _first_line(item: object) -> str:
    """An item's own `description` string if it has one (an instance such as a dataset
    format), else the first line of its docstring (a config class, a function)."""
    own = vars(item).get("description") if hasattr(item, "__dict__") else None
    text = own if isinstance(own, str) and own else (getattr(item, "__doc__", None) or "")
    return text.strip().splitlines()[0] if text.strip() else ""

"""Shared test setup: the built-in demo scene is generated once per session into a private
cache folder, never into the user's ~/.cache."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared"
DATA = SHARED / "data"
WEIGHTS = SHARED / "weights" / "torch-home"


def pytest_configure(config: pytest.Config) -> None:
    if "DYNGS_CACHE" not in os.environ:
        os.environ["DYNGS_CACHE"] = tempfile.mkdtemp(prefix="dyngs-test-cache-")


def shared_scene(name: str) -> Path:
    """A real scene from ../shared/data, or a skip saying why it is missing."""
    path = DATA / name
    if not path.is_dir():
        pytest.skip(
            f"shared dataset {path} is not present (tests with real data need ../shared/data)"
        )
    return path

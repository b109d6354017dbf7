"""Reading and checking the small metadata files every format has (JSON, numbers, arrays).

Every helper raises a one-line DatasetError naming the file (and the key) it choked on.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from jaxtyping import Float

from dyngs.errors import DatasetError


def load_json(path: Path) -> dict[str, Any]:
    """The top-level JSON object of `path`."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing") from None
    except OSError as error:
        raise DatasetError(f"{path}: cannot read ({error.strerror})") from None
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: not UTF-8 text") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as error:
        raise DatasetError(
            f"{path}: malformed JSON at line {error.lineno}, column {error.colno}: {error.msg}"
        ) from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: top level must be a JSON object, got {type(data).__name__}")
    return data


def require(data: dict[str, Any], key: str, where: str) -> Any:
    """data[key], or an error saying it is missing."""
    if key not in data:
        raise DatasetError(f"{where}: missing '{key}'")
    return data[key]


def number(value: object, key: str, where: str, positive: bool = False) -> float:
    """`value` as a finite float (a JSON number, not a bool); > 0 when `positive`."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise DatasetError(f"{where}: {key} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise DatasetError(f"{where}: {key} is not finite ({value})")
    if positive and value <= 0:
        raise DatasetError(f"{where}: {key} must be positive, got {value}")
    return float(value)


def whole(value: object, key: str, where: str) -> int:
    """`value` as a positive whole number (pixels, counts)."""
    number(value, key, where, positive=True)
    assert isinstance(value, int | float)
    if value != int(value):
        raise DatasetError(f"{where}: {key} must be a whole number, got {value}")
    return int(value)


def array(
    value: object, key: str, where: str, shape: tuple[int, ...]
) -> Float[np.ndarray, "*shape"]:
    """`value` as a finite float64 array of exactly `shape`."""
    if isinstance(value, bool | str) or value is None:
        raise DatasetError(f"{where}: {key} must be numbers of shape {list(shape)}, got {value!r}")
    try:
        result = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: {key} must be numbers of shape {list(shape)}") from None
    if result.shape != shape:
        raise DatasetError(f"{where}: {key} has shape {list(result.shape)}, need {list(shape)}")
    if not np.isfinite(result).all():
        raise DatasetError(f"{where}: {key} has non-finite entries")
    return result


_NPY_MAGIC = b"\x93NUMPY"


def load_npy(path: Path) -> np.ndarray:
    """A .npy array (no pickled objects)."""
    try:
        with path.open("rb") as stream:
            magic = stream.read(len(_NPY_MAGIC))
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing") from None
    except OSError as error:
        raise DatasetError(f"{path}: cannot read ({error.strerror})") from None
    if magic != _NPY_MAGIC:
        raise DatasetError(f"{path}: not a .npy file (no NumPy header)")
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as error:
        problem = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise DatasetError(f"{path}: not a readable .npy array ({problem})") from None

"""A small PLY reader and writer (numpy only).

`read_ply` understands the three standard encodings (ascii, binary_little_endian,
binary_big_endian) and every scalar property type; elements with `property list`
(faces, edges) are read past and dropped. `write_ply` writes one element of scalar
properties in binary little endian, which is what 3DGS-style point files need.

Letters: N vertices.
"""

from __future__ import annotations

from pathlib import Path
from typing import BinaryIO

import numpy as np
from jaxtyping import Shaped

from dyngs.errors import DatasetError

_TYPES: dict[str, str] = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
"""PLY scalar type names (both the classic and the sized spelling) → numpy kind+size."""

_WRITE_TYPES: dict[str, str] = {
    "i1": "char",
    "u1": "uchar",
    "i2": "short",
    "u2": "ushort",
    "i4": "int",
    "u4": "uint",
    "f4": "float",
}

_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}


class _Element:
    def __init__(self, name: str, count: int) -> None:
        self.name = name
        self.count = count
        # (name, scalar type) or (name, (count type, item type)) for a list property.
        self.properties: list[tuple[str, str | tuple[str, str]]] = []

    @property
    def has_lists(self) -> bool:
        return any(isinstance(kind, tuple) for _, kind in self.properties)


def _parse_header(stream: BinaryIO, path: Path) -> tuple[str, list[_Element]]:
    def fail(problem: str) -> DatasetError:
        return DatasetError(f"{path}: {problem}")

    if stream.readline().strip() != b"ply":
        raise fail("not a PLY file (no 'ply' magic line)")
    encoding: str | None = None
    elements: list[_Element] = []
    while True:
        raw = stream.readline()
        if not raw:
            raise fail("PLY header has no end_header line")
        try:
            words = raw.decode("ascii").split()
        except UnicodeDecodeError:
            raise fail("PLY header is not ASCII text") from None
        if not words or words[0] in ("comment", "obj_info"):
            continue
        keyword = words[0]
        if keyword == "end_header":
            break
        if keyword == "format":
            if len(words) < 2 or words[1] not in _FORMATS:
                raise fail(f"unknown PLY format {' '.join(words[1:])!r}")
            encoding = words[1]
        elif keyword == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise fail(f"bad PLY element line {raw.decode().strip()!r}")
            elements.append(_Element(words[1], int(words[2])))
        elif keyword == "property":
            if not elements:
                raise fail("PLY property before any element")
            if len(words) == 5 and words[1] == "list":
                count_type, item_type, name = words[2], words[3], words[4]
                if count_type not in _TYPES or item_type not in _TYPES:
                    raise fail(f"unknown PLY list type in {raw.decode().strip()!r}")
                elements[-1].properties.append((name, (count_type, item_type)))
            elif len(words) == 3 and words[1] in _TYPES:
                elements[-1].properties.append((words[2], words[1]))
            else:
                raise fail(f"bad PLY property line {raw.decode().strip()!r}")
        else:
            raise fail(f"unexpected PLY header line {raw.decode().strip()!r}")
    if encoding is None:
        raise fail("PLY header has no format line")
    return encoding, elements


def _read_binary(
    stream: BinaryIO, element: _Element, order: str, path: Path
) -> dict[str, np.ndarray] | None:
    """Read one element; returns None for elements with list properties (skipped)."""
    if not element.has_lists:
        dtype = np.dtype([(name, order + _TYPES[str(kind)]) for name, kind in element.properties])
        data = stream.read(dtype.itemsize * element.count)
        if len(data) != dtype.itemsize * element.count:
            raise DatasetError(f"{path}: PLY file is truncated in element {element.name!r}")
        table = np.frombuffer(data, dtype=dtype, count=element.count)
        return {
            name: table[name].astype(table[name].dtype.newbyteorder("="))
            for name, _ in element.properties
        }
    # Rows of varying length: walk them one by one just to find where the element ends.
    for _ in range(element.count):
        for _, kind in element.properties:
            if isinstance(kind, tuple):
                count_dtype = np.dtype(order + _TYPES[kind[0]])
                raw = stream.read(count_dtype.itemsize)
                if len(raw) != count_dtype.itemsize:
                    raise DatasetError(f"{path}: PLY file is truncated in element {element.name!r}")
                n = int(np.frombuffer(raw, dtype=count_dtype)[0])
                size = n * np.dtype(_TYPES[kind[1]]).itemsize
            else:
                size = np.dtype(_TYPES[kind]).itemsize
            if len(stream.read(size)) != size:
                raise DatasetError(f"{path}: PLY file is truncated in element {element.name!r}")
    return None


def _read_ascii(
    tokens: list[bytes], start: int, element: _Element, path: Path
) -> tuple[dict[str, np.ndarray] | None, int]:
    """Read one element from the token stream; returns its columns and the next token."""
    try:
        if not element.has_lists:
            width = len(element.properties)
            end = start + width * element.count
            if end > len(tokens):
                raise DatasetError(f"{path}: PLY file is truncated in element {element.name!r}")
            table = np.array(tokens[start:end], dtype=np.float64).reshape(element.count, width)
            columns = {
                name: table[:, i].astype(_TYPES[str(kind)])
                for i, (name, kind) in enumerate(element.properties)
            }
            return columns, end
        position = start
        for _ in range(element.count):
            for _, kind in element.properties:
                position += 1 + (int(tokens[position]) if isinstance(kind, tuple) else 0)
        if position > len(tokens):
            raise IndexError
        return None, position
    except (ValueError, IndexError):
        raise DatasetError(
            f"{path}: PLY ascii data of element {element.name!r} is malformed or truncated"
        ) from None


def read_ply_elements(path: Path | str) -> dict[str, dict[str, np.ndarray]]:
    """Every element made only of scalar properties, as {element: {property: column}}."""
    path = Path(path)
    try:
        stream = path.open("rb")
    except OSError as error:
        raise DatasetError(f"{path}: cannot open PLY file ({error.strerror})") from None
    with stream:
        encoding, elements = _parse_header(stream, path)
        result: dict[str, dict[str, np.ndarray]] = {}
        if encoding == "ascii":
            tokens = stream.read().split()
            position = 0
            for element in elements:
                columns, position = _read_ascii(tokens, position, element, path)
                if columns is not None:
                    result[element.name] = columns
        else:
            for element in elements:
                binary = _read_binary(stream, element, _FORMATS[encoding], path)
                if binary is not None:
                    result[element.name] = binary
    return result


def read_ply(path: Path | str) -> dict[str, np.ndarray]:
    """The properties of the `vertex` element by name, e.g. {"x": float32[N], ...}."""
    elements = read_ply_elements(path)
    if "vertex" not in elements:
        raise DatasetError(f"{path}: PLY file has no vertex element with scalar properties")
    return elements["vertex"]


def write_ply(
    path: Path | str,
    properties: dict[str, Shaped[np.ndarray, " N"]],
    element: str = "vertex",
) -> None:
    """Write one element of scalar properties, binary little endian.

    Float arrays are stored as float32 and bool as uchar; integer arrays keep their type
    (uint8 → uchar, int32 → int, …). 64-bit integers are refused rather than truncated.
    """
    if not properties:
        raise ValueError("write_ply needs at least one property")
    lengths = {name: np.shape(values) for name, values in properties.items()}
    first = next(iter(lengths.values()))
    if len(first) != 1 or any(shape != first for shape in lengths.values()):
        raise ValueError(f"write_ply needs 1-D arrays of one length, got shapes {lengths}")
    fields: list[tuple[str, str]] = []
    columns: list[np.ndarray] = []
    for name, values in properties.items():
        array = np.asarray(values)
        if not name or any(c.isspace() for c in name):
            raise ValueError(f"PLY property names cannot be empty or hold spaces: {name!r}")
        if array.dtype == np.bool_:
            array = array.astype(np.uint8)
        elif array.dtype.kind == "f":
            array = array.astype(np.float32)
        key = f"{array.dtype.kind}{array.dtype.itemsize}"
        if key not in _WRITE_TYPES:
            raise ValueError(f"write_ply cannot store property {name!r} of dtype {array.dtype}")
        fields.append((name, "<" + key))
        columns.append(array)
    table = np.empty(first[0], dtype=np.dtype(fields))
    for (name, _), column in zip(fields, columns, strict=True):
        table[name] = column
    header = ["ply", "format binary_little_endian 1.0", f"element {element} {first[0]}"]
    header += [f"property {_WRITE_TYPES[kind[1:]]} {name}" for name, kind in fields]
    header.append("end_header")
    with Path(path).open("wb") as stream:
        stream.write(("\n".join(header) + "\n").encode("ascii"))
        stream.write(table.tobytes())

"""The PLY reader and writer: round trips, the three encodings, list elements, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dyngs.errors import DatasetError
from dyngs.ply import read_ply, read_ply_elements, write_ply
from tests.datamanagers.fixtures import SHARED_DATA


def test_round_trip_keeps_names_order_and_values(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    n = 257
    props: dict[str, np.ndarray] = {
        "x": rng.normal(size=n).astype(np.float32),
        "y": rng.normal(size=n),  # float64 is stored as float32
        "opacity": rng.normal(size=n).astype(np.float32),
        "red": rng.integers(0, 256, n).astype(np.uint8),
        "label": rng.integers(-5, 5, n).astype(np.int32),
        "flag": rng.random(n) > 0.5,
    }
    write_ply(tmp_path / "a.ply", props)
    back = read_ply(tmp_path / "a.ply")
    assert list(back) == list(props)
    assert back["x"].dtype == np.float32 and back["y"].dtype == np.float32
    assert back["red"].dtype == np.uint8 and back["label"].dtype == np.int32
    np.testing.assert_array_equal(back["x"], props["x"])
    np.testing.assert_array_equal(back["y"], props["y"].astype(np.float32))
    np.testing.assert_array_equal(back["red"], props["red"])
    np.testing.assert_array_equal(back["label"], props["label"])
    np.testing.assert_array_equal(back["flag"], props["flag"].astype(np.uint8))
    header = (tmp_path / "a.ply").read_bytes().split(b"end_header\n")[0].decode()
    assert "format binary_little_endian 1.0" in header
    assert "property float y" in header and "property uchar red" in header


def test_write_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="one length"):
        write_ply(tmp_path / "b.ply", {"x": np.zeros(3), "y": np.zeros(4)})
    with pytest.raises(ValueError, match="int64"):
        write_ply(tmp_path / "b.ply", {"x": np.zeros(3, dtype=np.int64)})


HEADER = """ply
format {fmt} 1.0
comment written by hand
element vertex 2
property float x
property double y
property uchar red
element face 2
property list uchar int vertex_indices
element extra 1
property short s
end_header
"""


def test_ascii_and_big_endian_with_list_element_before_another(tmp_path: Path) -> None:
    ascii_body = "1.5 -2.25 7\n0 3 255\n3 0 1 1\n4 1 0 1 0\n-12\n"
    (tmp_path / "a.ply").write_text(HEADER.format(fmt="ascii") + ascii_body)
    vertex = np.array([(1.5, -2.25, 7), (0.0, 3.0, 255)], dtype=">f4, >f8, u1")
    faces = (
        np.array([3], ">u1").tobytes()
        + np.array([0, 1, 1], ">i4").tobytes()
        + np.array([4], ">u1").tobytes()
        + np.array([1, 0, 1, 0], ">i4").tobytes()
    )
    body = vertex.tobytes() + faces + np.array([-12], ">i2").tobytes()
    (tmp_path / "b.ply").write_bytes(HEADER.format(fmt="binary_big_endian").encode() + body)
    for name in ("a.ply", "b.ply"):
        elements = read_ply_elements(tmp_path / name)
        assert set(elements) == {"vertex", "extra"}  # the list element is skipped
        np.testing.assert_array_equal(elements["vertex"]["x"], [1.5, 0.0])
        np.testing.assert_array_equal(elements["vertex"]["y"], [-2.25, 3.0])
        np.testing.assert_array_equal(elements["vertex"]["red"], [7, 255])
        np.testing.assert_array_equal(elements["extra"]["s"], [-12])
        assert elements["vertex"]["y"].dtype == np.float64


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        (b"ply\nformat binary_middle_endian 1.0\nend_header\n", "unknown PLY format"),
        (b"not a ply\n", "not a PLY file"),
        (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n", "no end_header"),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
            b"end_header\n\x00\x00",
            "truncated",
        ),
        (b"ply\nformat ascii 1.0\nelement face 0\nend_header\n", "no vertex element"),
    ],
)
def test_bad_files_raise_one_line_naming_the_file(
    tmp_path: Path, content: bytes, problem: str
) -> None:
    path = tmp_path / "broken.ply"
    path.write_bytes(content)
    with pytest.raises(DatasetError, match=problem) as info:
        read_ply(path)
    assert "broken.ply" in str(info.value) and "\n" not in str(info.value)


def test_reads_the_shared_fused_point_cloud() -> None:
    path = SHARED_DATA / "mujoco-collision" / "fused.ply"
    if not path.is_file():
        pytest.skip(f"shared data absent: {path.resolve()} not found")
    vertex = read_ply(path)
    assert list(vertex) == ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"]
    assert all(len(column) == 100_000 for column in vertex.values())
    assert vertex["x"].dtype == np.float32 and vertex["red"].dtype == np.uint8
    assert np.isfinite(vertex["x"]).all()

"""A corpus of broken D-NeRF folders: each must fail with a one-line DatasetError that
names the offending file."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dyngs.datamanagers.dnerf import parse_dnerf
from dyngs.errors import DatasetError
from tests.datamanagers.fixtures import small_dataset

TRAIN = "transforms_train.json"


def _edit(split: str, change: Callable[[dict[str, Any]], None]) -> Callable[[Path], None]:
    """A breakage that edits transforms_{split}.json in place."""

    def apply(folder: Path) -> None:
        path = folder / f"transforms_{split}.json"
        meta = json.loads(path.read_text())
        change(meta)
        path.write_text(json.dumps(meta))  # writes NaN as the JSON extension NaN

    return apply


def _frame(index: int, **values: Any) -> Callable[[dict[str, Any]], None]:
    def change(meta: dict[str, Any]) -> None:
        meta["frames"][index].update(values)

    return change


def _drop(index: int, key: str) -> Callable[[dict[str, Any]], None]:
    def change(meta: dict[str, Any]) -> None:
        del meta["frames"][index][key]

    return change


def _matrix(
    index: int, edit: Callable[[np.ndarray], np.ndarray]
) -> Callable[[dict[str, Any]], None]:
    def change(meta: dict[str, Any]) -> None:
        frame = meta["frames"][index]
        frame["transform_matrix"] = edit(np.array(frame["transform_matrix"])).tolist()

    return change


def _scaled(m: np.ndarray) -> np.ndarray:
    m[:3, :3] *= 2.0
    return m


def _singular(m: np.ndarray) -> np.ndarray:
    m[:3, 0] = 0.0
    return m


def _reflected(m: np.ndarray) -> np.ndarray:
    m[:3, 0] = -m[:3, 0]
    return m


def _with_nan(m: np.ndarray) -> np.ndarray:
    m[1, 2] = np.nan
    return m


def _write_file(relative: str, content: bytes) -> Callable[[Path], None]:
    def apply(folder: Path) -> None:
        (folder / relative).write_bytes(content)

    return apply


def _delete(relative: str) -> Callable[[Path], None]:
    def apply(folder: Path) -> None:
        (folder / relative).unlink()

    return apply


def _resize_image(relative: str) -> Callable[[Path], None]:
    def apply(folder: Path) -> None:
        cv2.imwrite(str(folder / relative), np.zeros((7, 8, 4), np.uint8))

    return apply


def _set_top(key: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def change(meta: dict[str, Any]) -> None:
        meta[key] = value

    return change


def _duplicate(meta: dict[str, Any]) -> None:
    meta["frames"][2]["file_path"] = meta["frames"][0]["file_path"]


def _no_focal(meta: dict[str, Any]) -> None:
    del meta["camera_angle_x"]


# name → (breakage, text the message must contain: the offending file's name)
CASES: dict[str, tuple[Callable[[Path], None], str]] = {
    "malformed json": (_write_file(TRAIN, b'{"camera_angle_x": 0.7,\n "frames": [}'), "line 2"),
    "top level not an object": (_write_file(TRAIN, b"[1, 2]"), TRAIN),
    "missing frames": (_edit("train", lambda m: m.pop("frames")), TRAIN),
    "frames not a list": (_edit("train", _set_top("frames", {"a": 1})), TRAIN),
    "empty frames": (_edit("train", _set_top("frames", [])), TRAIN),
    "frame missing time": (_edit("train", _drop(1, "time")), TRAIN),
    "frame missing transform_matrix": (_edit("train", _drop(1, "transform_matrix")), TRAIN),
    "frame missing file_path": (_edit("train", _drop(1, "file_path")), TRAIN),
    "time not finite": (_edit("train", _frame(1, time=float("nan"))), TRAIN),
    "time above 1": (_edit("val", _frame(0, time=1.5)), "transforms_val.json"),
    "time below 0": (_edit("train", _frame(0, time=-0.1)), TRAIN),
    "time not a number": (_edit("train", _frame(0, time="0.5")), TRAIN),
    "missing image": (_delete("train/r_001.png"), "r_001"),
    "unreadable image": (_write_file("test/r_001.png", b"\x89PNG\r\n garbage"), "r_001.png"),
    "image of another size": (_resize_image("val/r_001.png"), "r_001.png"),
    "image size differs from w/h": (_edit("train", _frame(0, w=9, h=6)), "r_000.png"),
    "transform not 4x4": (_edit("train", _matrix(1, lambda m: m[:3])), TRAIN),
    "transform not numbers": (_edit("train", _frame(1, transform_matrix="eye")), TRAIN),
    "transform non-finite": (_edit("train", _matrix(1, _with_nan)), TRAIN),
    "transform singular": (_edit("train", _matrix(1, _singular)), TRAIN),
    "transform scaled": (_edit("train", _matrix(1, _scaled)), TRAIN),
    "transform reflected": (_edit("test", _matrix(0, _reflected)), "transforms_test.json"),
    "duplicate file path": (_edit("train", _duplicate), TRAIN),
    "nan intrinsics": (_edit("train", _frame(0, fl_x=float("nan"))), TRAIN),
    "negative focal length": (_edit("train", _set_top("fl_x", -3.0)), TRAIN),
    "no focal length": (_edit("train", _no_focal), TRAIN),
    "missing test split": (_delete("transforms_test.json"), "transforms_test.json"),
}


def test_every_broken_folder_fails_with_a_one_line_error_naming_the_file(tmp_path: Path) -> None:
    built = 0
    failures: list[str] = []
    for index, (name, (breakage, expected)) in enumerate(CASES.items()):
        folder = small_dataset(tmp_path / f"case{index:02d}")
        breakage(folder)
        built += 1
        try:
            parse_dnerf(folder)
        except DatasetError as error:
            message = str(error)
            if expected not in message:
                failures.append(f"{name}: message lacks {expected!r}: {message}")
            if "\n" in message:
                failures.append(f"{name}: message is not one line: {message!r}")
        else:
            failures.append(f"{name}: parsed without error")
    assert not failures, "\n".join(failures)
    assert built == len(CASES) == 27


def test_the_unbroken_fixture_parses(tmp_path: Path) -> None:
    scene = parse_dnerf(small_dataset(tmp_path / "ok"))
    assert (len(scene.train), len(scene.val), len(scene.test)) == (3, 2, 2)

"""Broken Panoptic, DyNeRF and Nerfies folders: each must fail with a one-line
DatasetError that names the offending file."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import torch

from dyngs.cli import main
from dyngs.datamanagers.datamanager import DataConfig, DataManager, load_scene
from dyngs.errors import DatasetError
from tests.datamanagers.formats import write_dynerf, write_nerfies, write_panoptic

Breakage = Callable[[Path], None]


def _edit_json(relative: str, change: Callable[[dict[str, Any]], None]) -> Breakage:
    def apply(folder: Path) -> None:
        path = folder / relative
        data = json.loads(path.read_text())
        change(data)
        path.write_text(json.dumps(data))

    return apply


def _write(relative: str, content: bytes) -> Breakage:
    def apply(folder: Path) -> None:
        (folder / relative).write_bytes(content)

    return apply


def _delete(relative: str) -> Breakage:
    return lambda folder: (folder / relative).unlink()


def _pop(key: str) -> Callable[[dict[str, Any]], None]:
    return lambda data: data.pop(key)


def _set(key: str, value: Any) -> Callable[[dict[str, Any]], None]:
    return lambda data: data.__setitem__(key, value)


def _panoptic_w2c(data: dict[str, Any]) -> None:
    data["w2c"][1][0][0][0] *= 2.0  # scaled: not a rigid transform


def _panoptic_k(data: dict[str, Any]) -> None:
    data["k"][0][1] = [[1.0, 2.0], [3.0, 4.0]]


def _panoptic_short_row(data: dict[str, Any]) -> None:
    data["fn"][1] = data["fn"][1][:-1]


def _panoptic_points(folder: Path) -> None:
    np.savez(folder / "init_pt_cld.npz", points=np.zeros((4, 7)))


def _small_image(relative: str) -> Breakage:
    def apply(folder: Path) -> None:
        assert cv2.imwrite(str(folder / relative), np.zeros((10, 10, 3), dtype=np.uint8))

    return apply


PANOPTIC: dict[str, tuple[Breakage, str]] = {
    # A missing test_meta.json or seg/ file is how public releases ship (test views are
    # then held out, a frame without a mask counts fully): test_panoptic_releases.py.
    "missing train meta": (_delete("train_meta.json"), "train_meta.json"),
    "malformed json": (_write("train_meta.json", b'{"w": 32,'), "train_meta.json"),
    "missing key": (_edit_json("train_meta.json", _pop("w2c")), "train_meta.json"),
    "missing size": (_edit_json("test_meta.json", _pop("h")), "test_meta.json"),
    "ragged lists": (_edit_json("train_meta.json", _panoptic_short_row), "train_meta.json"),
    "scaled w2c": (_edit_json("train_meta.json", _panoptic_w2c), "train_meta.json"),
    "bad intrinsics": (_edit_json("train_meta.json", _panoptic_k), "train_meta.json"),
    "missing image": (_delete("ims/1/000001.jpg"), "000001.jpg"),
    "unreadable image": (_write("ims/0/000000.jpg", b"not a jpeg"), "ims/0/000000.jpg"),
    "wrong image size": (_small_image("ims/3/000000.jpg"), "ims/3/000000.jpg"),
    "npz without data": (_panoptic_points, "init_pt_cld.npz"),
    "npz not an archive": (_write("init_pt_cld.npz", b"garbage"), "init_pt_cld.npz"),
}


def _poses(change: Callable[[np.ndarray], np.ndarray]) -> Breakage:
    def apply(folder: Path) -> None:
        np.save(folder / "poses_bounds.npy", change(np.load(folder / "poses_bounds.npy")))

    return apply


def _scaled_pose(poses: np.ndarray) -> np.ndarray:
    poses[1, 0] *= 3.0
    return poses


def _bad_bounds(poses: np.ndarray) -> np.ndarray:
    poses[2, 15:] = [4.0, 1.0]
    return poses


def _short_video(folder: Path) -> None:
    write_dynerf(folder, num_cameras=3, frames=4, short={2: 3})


DYNERF: dict[str, tuple[Breakage, str]] = {
    "short video": (_short_video, "cam02.mp4"),
    "undecodable video": (_write("cam01.mp4", b"\x00" * 64), "cam01.mp4"),
    "poses not npy": (_write("poses_bounds.npy", b"nonsense"), "poses_bounds.npy"),
    "poses wrong width": (_poses(lambda p: p[:, :15]), "poses_bounds.npy"),
    "poses fewer rows": (_poses(lambda p: p[:2]), "poses_bounds.npy"),
    "poses scaled rotation": (_poses(_scaled_pose), "poses_bounds.npy"),
    "poses bad bounds": (_poses(_bad_bounds), "poses_bounds.npy"),
    "poses nan": (_poses(lambda p: p * np.nan), "poses_bounds.npy"),
}


def _nerfies_orientation(data: dict[str, Any]) -> None:
    data["orientation"][0] = [1.0, 1.0, 0.0]


def _nerfies_metadata(data: dict[str, Any]) -> None:
    data.pop("000001")


def _nerfies_points(folder: Path) -> None:
    np.save(folder / "points.npy", np.zeros((5, 4)))


def _nerfies_no_rgb(folder: Path) -> None:
    shutil.rmtree(folder / "rgb")


NERFIES: dict[str, tuple[Breakage, str]] = {
    "missing train_ids": (_edit_json("dataset.json", _pop("train_ids")), "dataset.json"),
    "ids not a list": (_edit_json("dataset.json", _set("val_ids", 3)), "dataset.json"),
    "metadata lacks an id": (_edit_json("metadata.json", _nerfies_metadata), "metadata.json"),
    "missing metadata": (_delete("metadata.json"), "metadata.json"),
    "camera not json": (_write("camera/000001.json", b"{orientation"), "camera/000001.json"),
    "camera lacks focal": (
        _edit_json("camera/000002.json", _pop("focal_length")),
        "camera/000002.json",
    ),
    "camera not a rotation": (
        _edit_json("camera/000000.json", _nerfies_orientation),
        "camera/000000.json",
    ),
    "camera bad distortion": (
        _edit_json("camera/000000.json", _set("radial_distortion", "none")),
        "camera/000000.json",
    ),
    "missing camera": (_delete("camera/000003.json"), "camera/000003.json"),
    "image size mismatch": (
        _edit_json("camera/000004.json", _set("image_size", [64, 48])),
        "rgb/1x/000004.png",
    ),
    "missing image": (_delete("rgb/1x/000005.png"), "rgb/1x/000005.png"),
    "scene lacks scale": (_edit_json("scene.json", _pop("scale")), "scene.json"),
    "scene bad bounds": (_edit_json("scene.json", _set("far", -1.0)), "scene.json"),
    "no rgb folder": (_nerfies_no_rgb, "rgb"),
    "points wrong shape": (_nerfies_points, "points.npy"),
}


@pytest.fixture(scope="module")
def originals(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("originals")
    write_panoptic(root / "panoptic", num_train=4, timesteps=2)
    write_dynerf(root / "dynerf", num_cameras=3, frames=4)
    write_nerfies(root / "nerfies", frames=8, scales=(1,))
    return {name: root / name for name in ("panoptic", "dynerf", "nerfies")}


CASES = [
    pytest.param(fmt, breakage, expected, id=f"{fmt}: {name}")
    for fmt, corpus in (("panoptic", PANOPTIC), ("dynerf", DYNERF), ("nerfies", NERFIES))
    for name, (breakage, expected) in corpus.items()
]


@pytest.mark.parametrize(("fmt", "breakage", "expected"), CASES)
def test_broken_folder_fails_with_one_line_naming_the_file(
    fmt: str, breakage: Breakage, expected: str, originals: dict[str, Path], tmp_path: Path
) -> None:
    folder = tmp_path / fmt
    shutil.copytree(originals[fmt], folder)
    breakage(folder)
    with pytest.raises(DatasetError) as caught:
        load_scene(folder, DataConfig(num_random_points=20))
    message = str(caught.value)
    assert "\n" not in message
    assert expected in message, message


def test_a_frame_broken_after_parsing_fails_when_served(
    originals: dict[str, Path], tmp_path: Path
) -> None:
    """Images are read lazily: a bad frame the parser did not decode is reported, naming
    the file, when the datamanager reaches it (also from its read-ahead thread)."""
    folder = tmp_path / "panoptic"
    shutil.copytree(originals["panoptic"], folder)
    (folder / "ims" / "2" / "000001.jpg").write_bytes(b"truncated")
    scene = load_scene(folder, DataConfig(num_random_points=20))
    manager = DataManager(
        scene, DataConfig(device_cache_bytes=0), torch.device("cpu"), torch.Generator()
    )
    with pytest.raises(DatasetError, match=r"ims/2/000001\.jpg: cannot read image"):
        for _ in range(manager.num_views("train")):
            manager.next_train()


def test_cli_reports_a_short_video_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    write_dynerf(tmp_path / "scene", num_cameras=2, frames=3, short={1: 2})
    with pytest.raises(SystemExit) as exit_info:
        main(["hexplane-4dgs", "--data", str(tmp_path / "scene"), "--output-dir", str(tmp_path)])
    assert exit_info.value.code == 2
    lines = [line for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "cam01.mp4" in lines[0]

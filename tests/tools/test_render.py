"""dyngs-render: the MP4 opens with OpenCV with the expected frame count and size."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from dyngs.datamanagers.datamanager import DataConfig, load_scene
from dyngs.datamanagers.scene_info import SceneInfo
from dyngs.tools.render import look_at, main, spiral_cameras, world_up
from tests.engine.helpers import TINY_SCENE


def _video(path: Path) -> tuple[int, int, int, int]:
    """(frames counted by reading, frames in the header, width, height)."""
    capture = cv2.VideoCapture(str(path))
    assert capture.isOpened(), path
    header = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
    height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
    read = 0
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        assert frame.shape == (height, width, 3)
        read += 1
    capture.release()
    return read, header, width, height


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--trajectory", "spiral", "--frames", "5", "--width", "40", "--height", "24"],
         (5, 40, 24)),
        (["--trajectory", "test", "--scale", "2"], (TINY_SCENE.num_test, 64, 64)),
        (["--trajectory", "fixed", "--camera", "1", "--frames", "4", "--height", "16"],
         (4, 16, 16)),
        (["--frames", "2", "--width", "33", "--height", "17"], (2, 32, 16)),  # made even
    ],
    ids=["spiral", "test", "fixed", "odd-size"],
)  # fmt: skip
def test_video_frames_and_size(
    args: list[str], expected: tuple[int, int, int], tiny_run: Path, tmp_path: Path
) -> None:
    out = tmp_path / "video.mp4"
    main(["--load-dir", str(tiny_run), "--output", str(out), "--fps", "12", *args])
    frames, width, height = expected
    assert _video(out) == (frames, frames, width, height)


def test_bad_camera_index_is_one_line(
    tiny_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--load-dir", str(tiny_run), "--trajectory", "fixed", "--camera", "99",
              "--output", str(tmp_path / "x.mp4")])  # fmt: skip
    assert exit_info.value.code == 2
    assert "--camera 99" in capsys.readouterr().out


def test_look_at_centres_the_target_with_up_on_top() -> None:
    eye, target, up = np.array([3.0, -1.0, 2.0]), np.array([0.5, 0.2, -0.1]), np.array([0, 0, 1.0])
    w2c = look_at(eye, target, up)
    rotation = w2c[:3, :3]
    assert np.allclose(rotation @ rotation.T, np.eye(3)) and np.isclose(np.linalg.det(rotation), 1)
    seen = w2c @ np.append(target, 1.0)
    assert np.allclose(seen[:2], 0, atol=1e-12) and seen[2] > 0  # on the optical axis, ahead
    above = w2c @ np.append(target + up, 1.0)
    assert above[1] < 0  # image y points down, so world up is negative y


def test_world_up_snaps_to_a_near_axis_only() -> None:
    assert np.array_equal(world_up(np.array([-0.12, 0.1, 0.98])), [0.0, 0.0, 1.0])
    assert np.array_equal(world_up(np.array([0.0, -2.0, 0.1])), [0.0, -1.0, 0.0])
    tilted = np.array([0.0, 0.6, 0.8])
    assert np.allclose(world_up(tilted), tilted)
    assert np.array_equal(world_up(np.zeros(3)), [0.0, 0.0, 1.0])


def test_spiral_cameras_look_at_the_scene_centre(tiny_data: Path) -> None:
    scene = SceneInfo.of(load_scene(tiny_data, DataConfig()))
    cameras = spiral_cameras(scene, 6)
    centre = torch.tensor([*scene.scene_box.center, 1.0], dtype=torch.float32)
    distances = [float((c.center - centre[:3]).norm()) for c in cameras]
    assert max(distances) - min(distances) < 1e-4 * max(distances)
    for camera in cameras:
        seen = camera.world_to_camera @ centre
        assert seen[2] > 0 and seen[:2].abs().max() < 1e-4 * float(seen[2])

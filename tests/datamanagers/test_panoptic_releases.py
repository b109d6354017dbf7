"""Panoptic-style captures as public releases ship them: masks for some cameras only, no
test split, PNG where the metadata says JPEG, camera-to-world matrices under `w2c`, a
mirrored world frame. Each parses to the views it was rendered from, or, where it cannot
be used, fails with one line naming the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from dyngs.datamanagers.datamanager import DataConfig, load_scene
from dyngs.datamanagers.panoptic import HOLDOUT_EVERY, parse_panoptic
from dyngs.errors import ConfigError, DatasetError
from tests.datamanagers.formats import Release, known_points, project, write_panoptic
from tests.datamanagers.test_formats import _check_geometry


def test_masks_for_some_cameras_only(tmp_path: Path) -> None:
    write_panoptic(tmp_path, release=Release(seg_cameras=(0, 2)))
    scene = parse_panoptic(tmp_path)
    split = scene.train
    assert split.masks is not None and split.mask_known is not None
    assert split.mask_kind == "segmentation"
    for index in range(len(split)):
        camera_has_seg = index % 4 in (0, 2)  # four train cameras per timestep, in order
        assert split.has_mask(index) == camera_has_seg
        mask = split.masks[index]
        if camera_has_seg:
            assert set(mask.unique().tolist()) == {0, 255}
        else:  # every pixel counts
            assert bool((mask == 255).all())


def test_png_where_the_metadata_says_jpg(tmp_path: Path) -> None:
    truth = write_panoptic(tmp_path, release=Release(png=True))
    scene = parse_panoptic(tmp_path)
    _check_geometry(scene.train, truth.views["train"])
    assert scene.train.paths is not None and scene.train.paths[0].suffix == ".png"


@pytest.mark.parametrize(
    ("rule", "test_views"),
    [("every:3", lambda t, c: t % 3 == 1), ("camera:2", lambda t, c: c == 2)],
)
def test_without_test_meta_views_are_held_out_by_rule(
    tmp_path: Path,
    rule: str,
    test_views,
    capsys: pytest.CaptureFixture[str],  # type: ignore[no-untyped-def]
) -> None:
    truth = write_panoptic(tmp_path, timesteps=6, release=Release(test_meta=False))
    scene = parse_panoptic(tmp_path, holdout=rule)
    views = truth.views["train"]  # every view written, four cameras per timestep
    expected_test = [i for i in range(len(views)) if test_views(i // 4, i % 4)]
    assert len(scene.test) == len(expected_test) > 0
    assert len(scene.train) == len(views) - len(expected_test)
    _check_geometry(scene.test, [views[i] for i in expected_test])
    _check_geometry(scene.train, [v for i, v in enumerate(views) if i not in expected_test])
    said = capsys.readouterr().err
    assert "no test_meta.json: holding out" in said and rule in said


def test_auto_holdout_keeps_novel_times_for_few_cameras(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    write_panoptic(tmp_path, num_train=3, timesteps=12, release=Release(test_meta=False))
    scene = parse_panoptic(tmp_path)
    assert len(scene.test) == 3 * len([t for t in range(12) if t % 10 == HOLDOUT_EVERY // 2])
    assert f"every:{HOLDOUT_EVERY}" in capsys.readouterr().err


def test_auto_holdout_keeps_a_camera_for_many_cameras(tmp_path: Path) -> None:
    write_panoptic(tmp_path, num_train=5, timesteps=2, release=Release(test_meta=False))
    scene = parse_panoptic(tmp_path)
    assert len(scene.test) == 2 and len(scene.train) == 8
    assert len({tuple(c.world_to_camera.flatten().tolist()) for c in scene.test.cameras}) == 1


@pytest.mark.parametrize(
    "release",
    [
        Release(camera_to_world=True),
        Release(mirrored=True),
        Release(camera_to_world=True, mirrored=True),
    ],
    ids=["camera-to-world", "mirrored", "both"],
)
def test_camera_to_world_and_mirrored_releases_read_as_meant(
    tmp_path: Path, release: Release, capsys: pytest.CaptureFixture[str]
) -> None:
    truth = write_panoptic(tmp_path, release=release)
    scene = parse_panoptic(tmp_path)
    # Read as meant, every camera is the true one (the mirrored world is mirrored back),
    # and the point cloud lands where the scene is.
    _check_geometry(scene.train, truth.views["train"])
    _check_geometry(scene.test, truth.views["test"])
    said = capsys.readouterr().err
    assert ("camera-to-world" in said) == release.camera_to_world
    assert ("mirrored" in said) == release.mirrored
    camera = scene.train.cameras[0]
    w2c = camera.world_to_camera.double().numpy()
    depth = scene.points.double().numpy() @ w2c[2, :3] + w2c[2, 3]
    assert float(np.median(depth)) > 0


def test_mixed_handedness_is_refused_in_one_line(tmp_path: Path) -> None:
    import json

    write_panoptic(tmp_path)
    meta = json.loads((tmp_path / "train_meta.json").read_text())
    meta["w2c"][1][2] = (np.array(meta["w2c"][1][2]) @ np.diag([-1.0, 1, 1, 1])).tolist()
    (tmp_path / "train_meta.json").write_text(json.dumps(meta))
    with pytest.raises(
        DatasetError, match=r"train_meta.json: \[1\]\[2\]: w2c is a reflection"
    ) as error:
        parse_panoptic(tmp_path)
    assert "\n" not in str(error.value)


def test_a_holdout_that_cannot_be_used_says_why(tmp_path: Path) -> None:
    write_panoptic(tmp_path, release=Release(test_meta=False))
    with pytest.raises(DatasetError, match=r"train_meta.json: --holdout camera:9: no camera 9"):
        parse_panoptic(tmp_path, holdout="camera:9")
    for bad in ("every:1", "camera:x", "sometimes", "every:"):
        with pytest.raises(ConfigError, match="--holdout"):
            DataConfig(holdout=bad)


def test_known_points_project_into_the_held_out_views(tmp_path: Path) -> None:
    # The held-out views of a release without test_meta.json are ordinary views: the
    # cameras read back project the scene where it was rendered.
    truth = write_panoptic(tmp_path, timesteps=4, release=Release(test_meta=False, mirrored=True))
    scene = load_scene(tmp_path, DataConfig(holdout="camera:1", initial_points="file"))
    views = [v for i, v in enumerate(truth.views["train"]) if i % 4 == 1]
    for index, (camera, time) in enumerate(views):
        points = known_points(time)
        error = np.abs(project(scene.test.cameras[index], points) - project(camera, points)).max()
        assert error < 0.5
        assert float(scene.test.times[index]) == pytest.approx(time)
    assert torch.isfinite(scene.points).all()

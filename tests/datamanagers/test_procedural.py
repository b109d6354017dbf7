"""The procedural demo scene: deterministic, static when asked, parseable, and its
analytic geometry agrees with the images written."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from dyngs.datamanagers import procedural
from dyngs.datamanagers.dnerf import parse_dnerf
from dyngs.datamanagers.procedural import (
    ProceduralSceneConfig,
    capture,
    demo_path,
    is_on_dynamic_object,
    render_rgba,
    scene_objects,
    write_procedural_scene,
)

SMALL = ProceduralSceneConfig(resolution=48, num_times=4, views_per_time=2, num_test=2, num_val=1)


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("demo")
    write_procedural_scene(folder, SMALL)
    return folder


def _files(folder: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()
    }


def test_generation_is_deterministic(small_scene: Path, tmp_path: Path) -> None:
    write_procedural_scene(tmp_path, SMALL)
    first, second = _files(small_scene), _files(tmp_path)
    assert first.keys() == second.keys()
    assert "points3d.ply" in first and "train/r_007.png" in first
    assert all(first[name] == second[name] for name in first)


def test_motion_flag_controls_whether_images_change_over_time() -> None:
    camera, _ = capture(SMALL)["train"][0]
    still = ProceduralSceneConfig(resolution=48, motion=False)
    np.testing.assert_array_equal(render_rgba(still, camera, 0.2), render_rgba(still, camera, 0.7))
    moving = ProceduralSceneConfig(resolution=48)
    assert np.abs(render_rgba(moving, camera, 0.2) - render_rgba(moving, camera, 0.7)).max() > 0.5
    assert not any(obj.dynamic for obj in scene_objects(still, 0.5))
    assert {obj.name for obj in scene_objects(moving, 0.5) if obj.dynamic} == {"ball", "cube"}


def test_motion_start_holds_the_first_pose_then_plays_the_whole_motion() -> None:
    late = ProceduralSceneConfig(resolution=48, motion_start=0.5)
    moving = ProceduralSceneConfig(resolution=48)

    def centres(config: ProceduralSceneConfig, t: float) -> dict[str, np.ndarray]:
        return {obj.name: obj.center for obj in scene_objects(config, t)}

    for t in (0.0, 0.25, 0.5):  # still, at the t = 0 pose
        for name, centre in centres(late, t).items():
            np.testing.assert_array_equal(centre, centres(moving, 0.0)[name])
    for t_late, t in ((0.75, 0.5), (0.6, 0.2), (1.0, 1.0)):  # then twice as fast
        for name, centre in centres(late, t_late).items():
            np.testing.assert_allclose(centre, centres(moving, t)[name], atol=1e-12)
    assert procedural.config_key(late) != procedural.config_key(moving)
    with pytest.raises(ValueError, match="motion_start"):
        ProceduralSceneConfig(motion_start=1.0)


def test_the_default_scene_keeps_its_cache_key() -> None:
    # Fields added to the config after the first version leave the built-in scene's
    # folder in the cache where it was (a new key would render it again). A bump of
    # GENERATOR_VERSION changes it on purpose: then update it here.
    assert procedural.config_key(ProceduralSceneConfig()) == "cc42c9a3bb"


def test_written_folder_parses(small_scene: Path) -> None:
    scene = parse_dnerf(small_scene)
    assert (len(scene.train), len(scene.val), len(scene.test)) == (8, 1, 2)
    assert scene.num_timestamps == 4
    assert scene.train.masks is not None and scene.point_colors is not None
    assert 1000 < len(scene.points) < 5000
    # The cloud lies on the surfaces at t = 0.
    distances = np.min(
        [obj.signed_distance(scene.points.double().numpy()) for obj in scene_objects(SMALL, 0.0)],
        axis=0,
    )
    assert np.abs(distances).max() < 1e-4
    box = scene.scene_box
    assert all(lo < -0.85 and hi > 0.85 for lo, hi in zip(box.lower, box.upper, strict=True))
    # The test views sit between train times.
    assert set(scene.test.times.tolist()).isdisjoint(scene.train.times.tolist())


def test_written_poses_follow_the_blender_convention(small_scene: Path) -> None:
    """Each camera looks down its −z axis at the origin, with its +y axis pointing up."""
    meta = json.loads((small_scene / "transforms_train.json").read_text())
    for frame in meta["frames"]:
        c2w = np.array(frame["transform_matrix"])
        position = c2w[:3, 3]
        np.testing.assert_allclose(c2w[:3, 2], position / np.linalg.norm(position), atol=1e-9)
        assert c2w[2, 1] > 0.5  # elevation ≤ 50°: the camera's up is mostly world up


def test_images_show_the_analytic_ball_where_the_parsed_cameras_put_it(small_scene: Path) -> None:
    """Project the point of the ball nearest each camera through the *parsed* camera: the
    pixel there must be opaque and coloured like the ball's texture at that point."""
    scene = parse_dnerf(small_scene, background=(0.0, 0.0, 0.0))
    assert scene.train.masks is not None
    errors = []
    for camera, time, image, mask in zip(
        scene.train.cameras,
        scene.train.times.tolist(),
        scene.train.images,
        scene.train.masks,
        strict=True,
    ):
        objects = {obj.name: obj for obj in scene_objects(SMALL, time)}
        ball = objects["ball"]
        eye = camera.center.double().numpy()
        toward = (eye - ball.center) / np.linalg.norm(eye - ball.center)
        point = ball.center + ball.size[0] * toward
        direction = (point - eye) / np.linalg.norm(point - eye)
        nearest, _ = procedural.cast(list(objects.values()), eye, direction[None])
        if nearest[0] < np.linalg.norm(point - eye) - 1e-6:
            continue  # something stands in front of the ball from here
        w2c = camera.world_to_camera.double().numpy()
        x, y, z = w2c[:3, :3] @ point + w2c[:3, 3]
        u, v = camera.fx * x / z + camera.cx, camera.fy * y / z + camera.cy
        row, col = int(v), int(u)
        assert int(mask[row, col, 0]) == 255
        local = ball.to_local(point[None])
        expected = ball.shade(local, local / ball.size[0])[0]
        got = image[row, col].double().numpy() / 255.0
        # A pixel averages the texture over its footprint, so allow some blur.
        errors.append(np.abs(got - expected).max())
        assert errors[-1] < 0.25
        # …and the ball is dynamic there, while points on the static pillar are not.
        assert is_on_dynamic_object(point[None], time, SMALL)[0]
        pillar_top = objects["pillar"].center + np.array([0.0, 0.0, objects["pillar"].size[2]])
        assert not is_on_dynamic_object(pillar_top[None], time, SMALL)[0]
    assert len(errors) >= 4 and np.mean(errors) < 0.1


def test_demo_path_caches_and_never_leaves_half_written_folders(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("DYNGS_CACHE", str(tmp_path / "cache"))
    tiny = ProceduralSceneConfig(
        resolution=16, num_times=2, views_per_time=1, num_test=1, num_val=0
    )

    def interrupted(folder: Path, config: ProceduralSceneConfig) -> None:
        (folder / "transforms_train.json").write_text("{}")
        raise KeyboardInterrupt

    monkeypatch.setattr(procedural, "write_procedural_scene", interrupted)
    with pytest.raises(KeyboardInterrupt):
        demo_path(tiny)
    assert os.listdir(tmp_path / "cache") == []
    monkeypatch.undo()

    monkeypatch.setenv("DYNGS_CACHE", str(tmp_path / "cache"))
    path = demo_path(tiny)
    assert path.parent == tmp_path / "cache" and path.name.startswith("demo-")
    assert os.listdir(tmp_path / "cache") == [path.name]
    stamp = (path / "transforms_train.json").stat().st_mtime_ns
    assert demo_path(tiny) == path
    assert (path / "transforms_train.json").stat().st_mtime_ns == stamp
    assert demo_path(ProceduralSceneConfig(resolution=16, num_times=3, views_per_time=1)) != path
    scene = parse_dnerf(path)
    assert len(scene.val) == len(scene.test) == 1  # num_val=0: val falls back to test

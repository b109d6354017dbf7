"""Initial points from the data: a real cloud is kept, a noise cloud is replaced, and
points made from the images (carved, of what moves, triangulated, seeded along rays) lie
where the scene is. The procedural scene's analytic geometry is the ground truth."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from dyngs.datamanagers import init_points
from dyngs.datamanagers.datamanager import DataConfig, load_scene
from dyngs.datamanagers.fixed_cameras import FixedCameras
from dyngs.datamanagers.init_points import (
    aggregation_index,
    judge_cloud,
    seeded_along_rays,
    silhouette_agreement,
    silhouettes,
    triangulate,
)
from dyngs.datamanagers.procedural import (
    ProceduralSceneConfig,
    scene_objects,
    write_procedural_scene,
)
from dyngs.errors import ConfigError
from dyngs.ply import write_ply

MONOCULAR = ProceduralSceneConfig(resolution=48, num_times=8, views_per_time=2, num_test=2,
                                  num_val=1)  # fmt: skip
RIG = ProceduralSceneConfig(resolution=48, num_times=8, num_test=2, num_val=1, fixed_cameras=5)


def _distance_to_scene(
    points: torch.Tensor, config: ProceduralSceneConfig, times: int = 9
) -> np.ndarray:
    """Each point's distance to the nearest surface (or inside: ≤ 0) at any of `times`
    instants: carving pools what moves over time."""
    p = points.double().numpy()
    best = np.full(len(p), np.inf)
    for t in np.linspace(0, 1, times):
        for obj in scene_objects(config, float(t)):
            best = np.minimum(best, obj.signed_distance(p))
    return best


def _assert_near_the_scene(points: torch.Tensor, box: object) -> None:
    """Carved points sit on the scene (or in what it sweeps) where random points in the box
    mostly do not. Eight 48-pixel views make a loose hull: in measurements, 83 % of
    carved points lay within 0.25 of a surface (random points in the box: 12 %), their
    median 0.05-0.07 away (random: 0.72-0.76)."""
    carved = _distance_to_scene(points, MONOCULAR)
    lower, upper = torch.tensor(box.lower), torch.tensor(box.upper)  # type: ignore[attr-defined]
    gen = torch.Generator().manual_seed(5)
    uniform = lower + torch.rand(len(points), 3, generator=gen) * (upper - lower)
    random = _distance_to_scene(uniform, MONOCULAR)
    assert float((carved < 0.25).mean()) > 0.75 > 3 * float((random < 0.25).mean())
    assert float(np.median(carved)) < 0.2 * float(np.median(random))


def _write_noise(folder: Path, count: int = 5000, half: float = 3.0) -> None:
    xyz = np.random.default_rng(0).uniform(-half, half, size=(count, 3))
    grey = np.full(count, 128, dtype=np.uint8)
    write_ply(folder / "points3d.ply", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                                        "red": grey, "green": grey, "blue": grey})  # fmt: skip


@pytest.fixture
def monocular(tmp_path: Path) -> Path:
    write_procedural_scene(tmp_path, MONOCULAR)
    return tmp_path


def test_aggregation_index_tells_noise_from_surfaces() -> None:
    gen = torch.Generator().manual_seed(0)
    uniform = torch.rand(4000, 3, generator=gen) * torch.tensor([7.0, 3.0, 5.0])
    assert 0.85 < aggregation_index(uniform) < 1.2
    assert 0.85 < aggregation_index(uniform * 1e3 + 5) < 1.2  # no unit in it
    sphere = torch.randn(4000, 3, generator=gen)
    sphere = sphere / sphere.norm(dim=1, keepdim=True)
    assert aggregation_index(sphere) < init_points.NOISE_AGGREGATION
    blob = torch.randn(4000, 3, generator=gen)  # noise, but not uniform in a box
    assert aggregation_index(blob) >= init_points.NOISE_AGGREGATION


def test_a_flat_cloud_is_a_surface_not_noise() -> None:
    # Uniform on a plane is uniform in its (thin) box: R cannot tell it from noise, and a
    # floor seen from above is such a cloud. It is judged by its flatness instead.
    plane = torch.rand(4000, 3, generator=torch.Generator().manual_seed(1))
    plane[:, 2] = 0.5 + 1e-3 * plane[:, 2]
    assert init_points.is_flat(plane)
    assert judge_cloud(plane, None, None) is None  # type: ignore[arg-type]


def test_a_real_cloud_is_kept(monocular: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scene = load_scene(monocular, DataConfig())
    assert scene.points_source == "points3d.ply" and scene.points_on_surfaces
    assert "initial points from points3d.ply" in capsys.readouterr().err
    shapes = silhouettes(scene.train, scene.background)
    assert shapes is not None and shapes.kind == "alpha"
    assert judge_cloud(scene.points, scene.train, shapes) is None
    assert silhouette_agreement(scene.points, scene.train, shapes) > 0.9


def test_a_noise_cloud_is_replaced_by_points_carved_on_the_objects(
    monocular: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _write_noise(monocular)
    scene = load_scene(monocular, DataConfig(num_random_points=3000))
    said = capsys.readouterr().err
    assert "points3d.ply replaced, spread like uniform noise" in said
    assert scene.points_source.startswith("made from the images (") and scene.points_on_surfaces
    assert "alpha silhouettes" in scene.points_source
    assert 1000 <= len(scene.points) <= 3000 and scene.point_colors is not None
    _assert_near_the_scene(scene.points, scene.scene_box)
    # The box no longer stretches to the noise.
    assert max(np.array(scene.scene_box.upper) - np.array(scene.scene_box.lower)) < 4.0


def test_without_a_cloud_the_points_come_from_the_images(monocular: Path) -> None:
    (monocular / "points3d.ply").unlink()
    scene = load_scene(monocular, DataConfig(num_random_points=2000))
    assert scene.points_source.startswith("made from the images")
    _assert_near_the_scene(scene.points, scene.scene_box)


def test_initial_points_modes(monocular: Path) -> None:
    _write_noise(monocular, count=500)
    kept = load_scene(monocular, DataConfig(initial_points="file"))
    assert kept.points_source == "points3d.ply" and len(kept.points) == 500
    assert not kept.points_on_surfaces  # used as it is, unchecked
    made = load_scene(monocular, DataConfig(initial_points="data", num_random_points=800))
    assert made.points_source.startswith("made from the images") and made.points_on_surfaces
    drawn = load_scene(monocular, DataConfig(initial_points="random"))
    assert not drawn.points_on_surfaces
    with pytest.raises(ConfigError, match="--initial-points"):
        DataConfig(initial_points="carve")


def test_what_moves_gets_points_of_its_own_on_fixed_cameras(tmp_path: Path) -> None:
    write_procedural_scene(tmp_path, RIG)
    scene = load_scene(tmp_path, DataConfig(initial_points="data", num_random_points=2000))
    assert "what moves" in scene.points_source
    moving = init_points.moving_silhouettes(scene.train, 0.1)
    assert moving is not None
    box = scene.scene_box
    carved = init_points.carve(scene.train, moving, box, 600, seed=1)
    assert len(carved) > 300
    # On the ball or the cube at some time: their swept volume, not the still pedestal.
    p = carved.double().numpy()
    on_moving = np.full(len(p), np.inf)
    for t in np.linspace(0, 1, 17):
        for obj in scene_objects(RIG, float(t)):
            if obj.dynamic:
                on_moving = np.minimum(on_moving, obj.signed_distance(p))
    assert float((on_moving < 0.25).mean()) > 0.8


def test_points_seeded_along_rays_show_their_pixel(tmp_path: Path) -> None:
    write_procedural_scene(tmp_path, RIG)
    scene = load_scene(tmp_path, DataConfig(initial_points="file"))
    fixed = FixedCameras.of(scene.train)
    assert fixed is not None
    points, colors = seeded_along_rays(scene.train, scene.scene_box, 500, 3, fixed)
    assert len(points) == 500
    box = torch.tensor([scene.scene_box.lower, scene.scene_box.upper])
    assert bool(((points >= box[0] - 1e-4) & (points <= box[1] + 1e-4)).all())
    per_camera = 500 // len(fixed.cameras)
    camera, median = fixed.cameras[0], fixed.medians[0]
    w2c = camera.world_to_camera.double()
    local = points[:per_camera].double() @ w2c[:3, :3].T + w2c[:3, 3]
    u = (camera.fx * local[:, 0] / local[:, 2] + camera.cx).floor().long()
    v = (camera.fy * local[:, 1] / local[:, 2] + camera.cy).floor().long()
    assert torch.equal(median[v, u].float() / 255.0, colors[:per_camera])


@pytest.mark.slow
def test_triangulated_points_lie_on_the_surfaces(tmp_path: Path) -> None:
    config = ProceduralSceneConfig(resolution=128, num_times=4, views_per_time=3, num_test=1,
                                   num_val=1, motion=False)  # fmt: skip
    write_procedural_scene(tmp_path, config)
    scene = load_scene(tmp_path, DataConfig(initial_points="file"))
    found = triangulate(scene.train, scene.scene_box)
    assert len(found) > 50
    distance = np.abs(_distance_to_scene(found, config, times=1))
    # SIFT keypoints are located to a fraction of a pixel (a pixel is ~0.02 units here).
    assert float(np.median(distance)) < 0.03 and float((distance < 0.1).mean()) > 0.8


def test_a_capture_with_nothing_in_its_images_keeps_random_points(
    monocular: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Every image wholly the background colour: no silhouette to carve, nothing to match.
    import cv2

    for image in monocular.glob("*/r_*.png"):
        cv2.imwrite(str(image), np.full((48, 48, 3), 255, dtype=np.uint8))
    (monocular / "points3d.ply").unlink()
    scene = load_scene(monocular, DataConfig(num_random_points=300))
    assert scene.points_source == "random in the box" and len(scene.points) == 300
    assert not scene.points_on_surfaces
    assert "none could be made from the images" in capsys.readouterr().err


def test_the_first_window_holds_the_start_of_the_sequence(monocular: Path) -> None:
    scene = load_scene(monocular, DataConfig(initial_points="file"))
    spans = init_points.windows(scene.train, list(range(len(scene.train))))
    assert spans and min(float(scene.train.times[i]) for i in spans[0]) == 0.0
    flat = [i for span in spans for i in span]
    assert sorted(flat) == list(range(len(scene.train)))  # every view, once
    for span in spans:
        assert len(span) >= min(init_points.WINDOW_VIEWS, len(scene.train))
    assert math.isfinite(float(scene.points.sum()))

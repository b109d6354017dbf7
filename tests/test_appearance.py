"""Per-camera colour (`dyngs.appearance.CameraColours`): which cameras get one, what it
does to a render, that training learns it, and that checkpoints keep it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

from dyngs.appearance import CameraColours
from dyngs.config import TrainConfig
from dyngs.datamanagers.base import Split
from dyngs.datamanagers.datamanager import load_scene
from dyngs.datamanagers.procedural import ProceduralSceneConfig, demo_path
from dyngs.engine.evaluate import evaluate
from dyngs.engine.optim import OptimConfig
from dyngs.engine.trainer import Trainer
from dyngs.engine.writer import NullWriter
from dyngs.errors import ConfigError
from dyngs.model import DynamicGaussians
from dyngs.types import Camera
from tests.engine.helpers import tiny_config

RIG = ProceduralSceneConfig(resolution=32, num_times=8, fixed_cameras=3, num_test=2, num_val=0)


def _camera(x: float) -> Camera:
    world_to_camera = torch.eye(4)
    world_to_camera[0, 3] = -x  # centre at (x, 0, 0)
    return Camera(20.0, 20.0, 8.0, 8.0, world_to_camera, 16, 16)


def _photographs(xs: list[float]) -> Split:
    """A training split of photographs, one view at each of len(xs) times, from cameras
    centred at (x, 0, 0)."""
    images = [torch.zeros(16, 16, 3, dtype=torch.uint8) for _ in xs]
    times = torch.linspace(0, 1, len(xs))
    return Split(cameras=[_camera(x) for x in xs], times=times, images=images)


def test_only_cameras_seen_three_times_get_a_colour() -> None:
    colours = CameraColours.for_split(_photographs([0, 1, 0, 2, 0, 1, 1, 3, 2]))  # 0, 1: thrice
    assert colours is not None
    assert colours.centres.tolist() == [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]
    assert [colours.row(_camera(x)) for x in (0, 1, 2, 3)] == [0, 1, None, None]


def test_a_moving_camera_gets_none_nor_does_a_single_fixed_one() -> None:
    assert CameraColours.for_split(_photographs([0.1 * i for i in range(20)])) is None
    assert CameraColours.for_split(_photographs([0.0] * 5 + [1.0])) is None


def test_a_camera_draws_in_its_colour_centred_over_the_cameras() -> None:
    colours = CameraColours(torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]]))
    rgb = torch.rand(16, 16, 3)
    for x in (0, 1, 2, 5):  # zeros: every camera draws the image as it is
        assert torch.equal(colours(rgb, _camera(x)), rgb)
    with torch.no_grad():
        colours.log_gains.copy_(torch.tensor([[0.3, 0.0, -0.3], [0.0, 0.0, 0.0], [0.6, 0.3, 0.0]]))
        colours.offsets.copy_(torch.tensor([[0.1, 0.0, 0.0], [0.0, 0.0, 0.0], [-0.1, 0.0, 0.3]]))
    gain = torch.tensor([0.0, -0.1, -0.2])  # camera 0's minus the mean over the three
    offset = torch.tensor([0.1, 0.0, -0.1])
    torch.testing.assert_close(colours(rgb, _camera(0)), rgb * gain.exp() + offset)
    assert torch.equal(colours(rgb, _camera(5)), rgb)  # not a camera of the rig: the mean


def test_a_rig_of_one_camera_has_nothing_to_correct() -> None:
    colours = CameraColours(torch.zeros(1, 3))
    with torch.no_grad():
        colours.log_gains.fill_(0.5)
    rgb = torch.rand(4, 4, 3)
    assert torch.equal(colours(rgb, _camera(0)), rgb)


def _rig_scene_with_a_dark_camera(factor: float):  # type: ignore[no-untyped-def]
    scene = load_scene(demo_path(RIG), tiny_config().dataset)
    dark = scene.train.cameras[0].viewpoint()
    images = [
        (image.float() * factor).round().to(torch.uint8) if camera.viewpoint() == dark else image
        for camera, image in zip(scene.train.cameras, scene.train.images, strict=True)
    ]
    # As photographs: the procedural scene is rendered with alpha, which gets no colours.
    train = dataclasses.replace(scene.train, images=images, masks=None)
    return dataclasses.replace(scene, train=train)


def _rig_trainer(tmp_path: Path, optim: OptimConfig, factor: float = 0.7) -> Trainer:
    config: TrainConfig = tiny_config(data=str(demo_path(RIG)), optim=optim, max_iters=150)
    return Trainer(config, tmp_path, NullWriter(), scene=_rig_scene_with_a_dark_camera(factor))


def test_training_learns_the_colour_of_a_darker_camera(tmp_path: Path) -> None:
    """One camera of three sees the scene 30 % darker. After training, its colour draws
    the scene's pixels at 0.7 ± 0.1 of the brightness the other two draw them at (its
    gain and offset together), where before training all three drew them alike."""
    trainer = _rig_trainer(tmp_path, OptimConfig(camera_colours=1e-2))
    colours, cameras = trainer.model.colours, trainer.scene.train.cameras
    assert colours is not None and len(colours) == 3
    rows = [colours.row(camera) for camera in cameras]
    firsts = [cameras[rows.index(row)] for row in range(3)]
    pixels = torch.stack(list(trainer.scene.train.images)).float().div(255)
    for step in range(trainer.config.steps):
        trainer.train_step(step)
    with torch.no_grad():
        drawn = [float(colours(pixels, camera).mean()) for camera in firsts]
    dark = rows[0]
    assert dark is not None
    others = sum(drawn) - drawn[dark]
    assert drawn[dark] / (others / 2) == pytest.approx(0.7, abs=0.1)


def test_without_a_rate_no_camera_gets_a_colour(tmp_path: Path) -> None:
    trainer = _rig_trainer(tmp_path, OptimConfig(camera_colours=0.0))
    assert trainer.model.colours is None
    assert "camera_colours" not in {g["name"] for g in trainer.optimizer.param_groups}


def test_a_negative_rate_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"--optim\.camera-colours must be ≥ 0"):
        OptimConfig(camera_colours=-1.0)


def test_a_saved_model_keeps_its_camera_colours(tmp_path: Path) -> None:
    trainer = _rig_trainer(tmp_path, OptimConfig())
    model = trainer.model
    assert model.colours is not None
    with torch.no_grad():
        model.colours.log_gains.normal_()
        model.colours.offsets.normal_()
    config = trainer.config
    again = DynamicGaussians.load(config.gaussians, config.field, config.head, model.state_dict())
    rgb, camera = torch.rand(8, 8, 3), trainer.scene.train.cameras[0]
    assert torch.equal(again.camera_colour(rgb, camera), model.camera_colour(rgb, camera))
    assert not torch.equal(model.camera_colour(rgb, camera), rgb)


def test_a_model_saved_before_camera_colours_loads_without_them(tmp_path: Path) -> None:
    trainer = _rig_trainer(tmp_path, OptimConfig())
    config = trainer.config
    state = {k: v for k, v in trainer.model.state_dict().items() if not k.startswith("colours.")}
    again = DynamicGaussians.load(config.gaussians, config.field, config.head, state)
    assert again.colours is None
    rgb = torch.rand(8, 8, 3)
    assert again.camera_colour(rgb, trainer.scene.train.cameras[0]) is rgb


def test_evaluation_draws_each_view_in_its_cameras_colour(tmp_path: Path) -> None:
    """A test view from one of the rig's cameras is scored in that camera's colour, and one
    from a novel camera (the procedural scene's own test views) in the average colour."""
    scene = _rig_scene_with_a_dark_camera(1.0)
    train = scene.train
    seen = dataclasses.replace(train, cameras=train.cameras[:2], times=train.times[:2],
                               images=list(train.images[:2]))  # fmt: skip
    config = tiny_config(data=str(demo_path(RIG)))
    trainer = Trainer(config, tmp_path, NullWriter(), scene=dataclasses.replace(scene, test=seen,
                      val=scene.test))  # fmt: skip
    colours = trainer.model.colours
    assert colours is not None

    def psnr(split: str) -> float:
        metrics = evaluate(trainer.model, trainer.renderer, trainer.data, split, None,
                           trainer.device, warmup=0)  # fmt: skip
        return float(metrics["psnr"])

    before = {split: psnr(split) for split in ("test", "val")}
    row = colours.row(train.cameras[0])
    assert row is not None
    with torch.no_grad():
        colours.log_gains[row] = 0.6
    assert abs(psnr("test") - before["test"]) > 0.1
    assert psnr("val") == before["val"]


def test_rgba_renders_get_no_camera_colours() -> None:
    """One virtual camera drew a synthetic scene's RGBA images (the procedural rig's): its
    cameras stay put, and still none gets a colour of its own; the same frames as
    photographs, or with segmentation masks, do."""
    renders = load_scene(demo_path(RIG), tiny_config().dataset).train
    assert renders.masks is not None and renders.mask_kind == "alpha"
    assert CameraColours.for_split(renders) is None
    assert CameraColours.for_split(dataclasses.replace(renders, masks=None)) is not None
    segmented = dataclasses.replace(renders, mask_kind="segmentation")
    assert CameraColours.for_split(segmented) is not None

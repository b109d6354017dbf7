"""DataManager: epochs, reproducible shuffling, resuming; load_scene's format detection."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from dyngs.datamanagers.base import LazyImages, SceneData, Split
from dyngs.datamanagers.datamanager import DataConfig, DataManager, load_scene
from dyngs.errors import ConfigError, DatasetError
from dyngs.types import Camera, SceneBox
from tests.datamanagers.fixtures import small_dataset


def _split(count: int, offset: int = 0, masks: bool = False) -> Split:
    cameras = [Camera.from_fov(1.0, 4, 3, torch.eye(4)) for _ in range(count)]
    images = [torch.full((3, 4, 3), offset + i, dtype=torch.uint8) for i in range(count)]
    return Split(
        cameras,
        torch.linspace(0, 1, count),
        images,
        [torch.full((3, 4, 1), 255, dtype=torch.uint8) for _ in range(count)] if masks else None,
    )


def _scene(num_train: int = 7) -> SceneData:
    return SceneData(
        name="toy",
        train=_split(num_train, masks=True),
        val=_split(2, offset=100),
        test=_split(3, offset=200),
        scene_box=SceneBox((-1, -1, -1), (1, 1, 1)),
        points=torch.zeros(5, 3),
        point_colors=None,
        background=torch.ones(3),
    )


DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def _manager(seed: int, cache_bytes: int = 2 << 30, device: str = "cpu") -> DataManager:
    config = DataConfig(device_cache_bytes=cache_bytes)
    generator = torch.Generator().manual_seed(seed)
    return DataManager(_scene(), config, torch.device(device), generator)


def _indices(manager: DataManager, count: int) -> list[int]:
    return [manager.next_train().index for _ in range(count)]


def test_each_epoch_serves_every_frame_once_in_a_new_order() -> None:
    manager = _manager(0)
    epochs = [_indices(manager, 7) for _ in range(4)]
    assert all(sorted(epoch) == list(range(7)) for epoch in epochs)
    assert len({tuple(epoch) for epoch in epochs}) == 4
    assert manager.epoch == 3


def test_order_is_reproducible_from_the_generator() -> None:
    assert _indices(_manager(5), 30) == _indices(_manager(5), 30)
    assert _indices(_manager(5), 30) != _indices(_manager(6), 30)


def test_state_dict_resumes_the_same_sequence() -> None:
    reference = _manager(1)
    _indices(reference, 10)
    state = reference.state_dict()
    expected = _indices(reference, 20)
    resumed = _manager(99)  # a different generator: the state alone decides
    resumed.load_state_dict(state)
    assert _indices(resumed, 20) == expected
    with pytest.raises(ValueError, match="train views"):
        DataManager(
            _scene(num_train=4), DataConfig(), torch.device("cpu"), torch.Generator()
        ).load_state_dict(state)


def _frontier(manager: DataManager, max_time: float, span: float, count: int) -> list[int]:
    return [manager.next_frontier(max_time, span).index for _ in range(count)]


# Train times are k/6, k = 0..6: (window, span, the views a frontier draw may give).
FRONTIER_CASES = [
    (0.6, 0.3, {2, 3}),  # 1/3 and 1/2 lie in [0.3, 0.6]
    (0.9, 0.5, {3, 4, 5}),
    (1.0, 0.1, {6}),
    (0.6, 0.05, {3}),  # none in [0.55, 0.6]: the latest view before 0.6
    (0.01, 0.2, {0}),  # the window holds the first view alone
    (-1.0, 0.2, {0}),  # before the first view: the earliest stands in, as in next_train
]


@pytest.mark.parametrize(("window", "span", "expected"), FRONTIER_CASES)
def test_frontier_draws_come_from_the_newest_span_of_the_window(
    window: float, span: float, expected: set[int]
) -> None:
    assert set(_frontier(_manager(0), window, span, 60)) == expected


def test_frontier_draws_are_reproducible_resumable_and_leave_the_epochs_alone() -> None:
    plain, mixed = _manager(3), _manager(3)
    drawn = []
    for _ in range(12):  # interleaving frontier draws does not change the epochs' order
        drawn += _frontier(mixed, 1.0, 0.9, 2)
        assert plain.next_train().index == mixed.next_train().index
    assert _frontier(_manager(3), 1.0, 0.9, 24) == drawn  # the same from the same seed
    assert len(set(drawn)) > 3  # and random among the six candidates
    state = mixed.state_dict()
    expected = _frontier(mixed, 1.0, 0.9, 10)
    resumed = _manager(42)
    resumed.load_state_dict(state)
    assert _frontier(resumed, 1.0, 0.9, 10) == expected
    del state["frontier_draws"]  # a checkpoint from before frontier draws existed
    resumed.load_state_dict(state)
    assert _frontier(resumed, 1.0, 0.9, 24) == drawn


# Train times are k/6, k = 0..6: (window, limit, the views train_poses gives, in order).
POSE_CASES = [
    (1.0, 0, [0, 1, 2, 3, 4, 5, 6]),
    (0.5, 0, [0, 1, 2, 3]),  # 3/6 = 0.5 is inside the window
    (0.49, 0, [0, 1, 2]),
    (-1.0, 0, [0]),  # before the first view: the earliest stands in, as in next_train
    (1.0, 3, [0, 2, 4]),  # spread over the seven: i·7 // 3
    (1.0, 7, [0, 1, 2, 3, 4, 5, 6]),
    (0.5, 9, [0, 1, 2, 3]),  # a limit above the count gives them all
]


@pytest.mark.parametrize(("window", "limit", "expected"), POSE_CASES)
def test_train_poses_are_the_windows_views_in_time_order(
    window: float, limit: int, expected: list[int]
) -> None:
    manager = _manager(0)
    poses = manager.train_poses(window, limit)
    split = manager.scene.train
    assert [t for _, t in poses] == [float(split.times[i]) for i in expected]
    for (camera, _), i in zip(poses, expected, strict=True):
        assert torch.equal(camera.world_to_camera, split.cameras[i].world_to_camera)
    before = manager.state_dict()
    manager.train_poses(1.0)
    assert manager.state_dict() == before  # the training sequence is untouched
    with pytest.raises(ValueError, match="limit must be"):
        manager.train_poses(1.0, -1)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("cache_bytes", [2 << 30, 0])
def test_batches_are_float_images_whether_cached_or_not(cache_bytes: int, device: str) -> None:
    manager = _manager(0, cache_bytes, device)
    batch = manager.next_train()
    assert batch.image.dtype == torch.float32 and tuple(batch.image.shape) == (3, 4, 3)
    assert batch.image.device.type == device
    assert batch.camera.world_to_camera.device.type == device
    expected = torch.full((3, 4, 3), batch.index / 255.0, device=device)
    torch.testing.assert_close(batch.image, expected)
    assert batch.mask is not None and bool((batch.mask == 1.0).all())
    assert batch.time == pytest.approx(batch.index / 6)
    val = list(manager.views("val"))
    assert [b.index for b in val] == [0, 1]
    assert float(val[1].image[0, 0, 0]) == pytest.approx(101 / 255)
    assert val[0].mask is None
    assert manager.num_views("test") == 3
    with pytest.raises(ValueError, match="unknown split"):
        list(manager.views("validation"))


def test_load_scene_detects_formats_and_explains_failures(tmp_path: Path) -> None:
    scene = load_scene(small_dataset(tmp_path / "scene"), DataConfig(downscale=2))
    assert len(scene.train) == 3 and scene.train.cameras[0].width == 4
    with pytest.raises(DatasetError, match="does not exist"):
        load_scene(tmp_path / "missing", DataConfig())
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match=r"not a dataset folder.*transforms_train\.json"):
        load_scene(tmp_path / "empty", DataConfig())


def test_data_config_rejects_nonsense() -> None:
    with pytest.raises(ConfigError, match="downscale"):
        DataConfig(downscale=0)
    with pytest.raises(ConfigError, match="background"):
        DataConfig(background=(2.0, 0.0, 0.0))


def test_demo_is_the_procedural_scene(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from dyngs.datamanagers import datamanager

    folder = small_dataset(tmp_path / "scene")
    monkeypatch.setattr(datamanager, "demo_path", lambda: folder)
    assert len(load_scene("demo", DataConfig()).train) == 3


FRAME_BYTES = 6 * 8 * 3
"""A lazy test frame as uint8."""


def _lazy_scene(count: int, cache_bytes: int) -> tuple[SceneData, list[int]]:
    """A scene whose train split is `count` lazily read 6×8 frames; `reads` logs each read."""
    reads: list[int] = []

    def load(index: int) -> np.ndarray:
        reads.append(index)
        return np.full((6, 8, 3), index % 256, dtype=np.uint8)

    images = LazyImages(load, [(6, 8)] * count, 3, cache_bytes)
    cameras = [Camera.from_fov(1.0, 8, 6, torch.eye(4))] * count
    train = Split(cameras, torch.linspace(0, 1, count), images)
    scene = _scene()
    scene.train = train
    return scene, reads


@pytest.mark.parametrize("device", DEVICES)
def test_a_large_lazy_split_is_served_without_loading_every_frame(device: str) -> None:
    # 1000 frames, a host cache of 10 frames, a device budget of 4 KB (7 float frames).
    scene, reads = _lazy_scene(1000, cache_bytes=10 * FRAME_BYTES)
    config = DataConfig(device_cache_bytes=4096)
    manager = DataManager(scene, config, torch.device(device), torch.Generator().manual_seed(0))
    assert reads == []  # planning memory read no frame
    batches = [manager.next_train() for _ in range(25)]
    images = scene.train.images
    assert isinstance(images, LazyImages)
    # Each served frame is read once, plus the one read ahead for the next step.
    assert len(reads) <= 26 and images.loads == len(reads)
    assert {b.index for b in batches} <= set(reads)
    assert images.cached_bytes <= 10 * FRAME_BYTES
    for batch in batches:
        assert batch.image.dtype == torch.float32 and batch.image.device.type == device
        assert float(batch.image[0, 0, 0]) == pytest.approx((batch.index % 256) / 255)


def test_lazy_images_cache_is_bounded_and_reused() -> None:
    scene, reads = _lazy_scene(5, cache_bytes=2 * FRAME_BYTES)
    images = scene.train.images
    assert isinstance(images, LazyImages) and images.size(3) == (6, 8)
    first = images[0]
    assert images[0] is first and reads == [0]  # from the cache
    _ = images[1], images[2]  # evicts frame 0 (least recently used)
    assert images.cached_bytes == 2 * FRAME_BYTES
    _ = images[0]
    assert reads == [0, 1, 2, 0]
    assert [int(image[0, 0, 0]) for image in images[1:4]] == [1, 2, 3]
    with pytest.raises(IndexError):
        images[5]


def test_a_small_lazy_split_is_converted_once_onto_the_device() -> None:
    scene, reads = _lazy_scene(12, cache_bytes=0)
    manager = DataManager(scene, DataConfig(), torch.device("cpu"), torch.Generator())
    assert sorted(reads) == list(range(12))  # read once, kept as float
    for _ in range(30):
        manager.next_train()
    assert sorted(reads) == list(range(12))

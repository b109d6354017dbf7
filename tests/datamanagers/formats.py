"""Tiny captures in the Panoptic, DyNeRF and Nerfies layouts, rendered from the procedural
scene through known cameras.

Each writer returns the ground truth: per split, the (camera, time) of every view in the
order its parser should list them. The on-disk camera encodings (LLFF columns, Nerfies
orientation/position in an offset and scaled world) are written here straight from
each format's description, not with the parsers' helpers, so the tests check the parsers
against the conventions rather than against themselves.

Letters: N points, H×W image.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from jaxtyping import Float

from dyngs.datamanagers.procedural import (
    ProceduralSceneConfig,
    look_at,
    render_rgba,
    sample_point_cloud,
    scene_objects,
)
from dyngs.ply import write_ply
from dyngs.types import Camera

SCENE = ProceduralSceneConfig(resolution=32, seed=0)
"""Only its motion and seed matter here: the cameras below set the image size."""
BACKGROUND = (1.0, 1.0, 1.0)


@dataclass
class Truth:
    """What a parser should recover: (camera, time) per view, per split."""

    views: dict[str, list[tuple[Camera, float]]]


def ring_camera(
    azimuth: float,
    elevation: float,
    size: tuple[int, int],
    radius: float = 3.5,
    focal: tuple[float, float] | None = None,
    principal: tuple[float, float] | None = None,
) -> Camera:
    """A camera `radius` from the origin looking at it; focal lengths and principal point
    default to a 45° horizontal field of view, centred."""
    eye = radius * np.array(
        [
            math.cos(elevation) * math.cos(azimuth),
            math.cos(elevation) * math.sin(azimuth),
            math.sin(elevation),
        ]
    )
    width, height = size
    f = 0.5 * width / math.tan(math.radians(22.5))
    fx, fy = focal if focal is not None else (f, f)
    cx, cy = principal if principal is not None else (width / 2, height / 2)
    w2c = torch.from_numpy(look_at(eye)).float()
    return Camera(fx, fy, cx, cy, w2c, width, height)


def render_rgb(camera: Camera, t: float) -> np.ndarray:
    """uint8 RGB of the scene over BACKGROUND (real captures have no alpha)."""
    rgba = render_rgba(SCENE, camera, t)
    rgb = rgba[..., :3] * rgba[..., 3:] + np.asarray(BACKGROUND) * (1 - rgba[..., 3:])
    return np.round(rgb * 255).astype(np.uint8)


def known_points(t: float) -> Float[np.ndarray, "N 3"]:
    """The scene's object centres at t and a few fixed points around the origin."""
    centres = np.stack([obj.center for obj in scene_objects(SCENE, t)])
    rng = np.random.default_rng(7)
    return np.concatenate([centres, rng.uniform(-0.6, 0.6, size=(6, 3))])


def project(camera: Camera, points: Float[np.ndarray, "N 3"]) -> Float[np.ndarray, "N 2"]:
    """Pinhole projection in pixels (centres at +0.5), straight from the definition."""
    w2c = camera.world_to_camera.double().numpy()
    local = points @ w2c[:3, :3].T + w2c[:3, 3]
    u = camera.fx * local[:, 0] / local[:, 2] + camera.cx
    v = camera.fy * local[:, 1] / local[:, 2] + camera.cy
    return np.stack([u, v], axis=1)


def _write_png(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))


def _time(step: int, count: int) -> float:
    return step / max(count - 1, 1)


# ---------------------------------------------------------------- Panoptic


@dataclass(frozen=True)
class Release:
    """How a public Panoptic-style release departs from the layout's description."""

    seg_cameras: tuple[int, ...] | None = None
    """Cameras that have seg/ files (None: all)."""
    test_meta: bool = True
    """Whether test_meta.json is written (else its cameras are left out altogether)."""
    png: bool = False
    """Images are PNG files while `fn` names .jpg."""
    camera_to_world: bool = False
    """`w2c` holds the camera-to-world matrix."""
    mirrored: bool = False
    """The world frame is mirrored in x (every camera matrix a reflection, det −1)."""


MIRROR = np.diag([-1.0, 1.0, 1.0, 1.0])


def _pose_entry(camera: Camera, release: Release) -> list[list[float]]:
    """A camera's `w2c` as the release writes it."""
    w2c = camera.world_to_camera.double().numpy()
    if release.mirrored:  # the same camera in a world mirrored in x
        w2c = w2c @ MIRROR
    if release.camera_to_world:
        w2c = np.linalg.inv(w2c)
    return w2c.tolist()


def write_panoptic(
    folder: Path,
    num_train: int = 4,
    num_test: int = 1,
    timesteps: int = 3,
    size: tuple[int, int] = (32, 24),
    seg: bool = True,
    point_cloud: bool = True,
    release: Release = Release(),
) -> Truth:
    """train_meta.json / test_meta.json, ims/<cam>/<t>.jpg, seg/<cam>/<t>.png (0/1) and
    init_pt_cld.npz. Cameras have fx ≠ fy and an off-centre principal point. `release`
    writes the departures of real releases (the world then stays the true one: a mirrored
    release's points are mirrored too)."""
    width, height = size
    cameras = [
        ring_camera(
            2 * math.pi * c / (num_train + num_test) + 0.3,
            math.radians(25 + 10 * (c % 2)),
            size,
            focal=(0.9 * width, 0.95 * width),
            principal=(width / 2 + 1.3, height / 2 - 0.7),
        )
        for c in range(num_train + num_test)
    ]
    splits = {"train": list(range(num_train)), "test": list(range(num_train, num_train + num_test))}
    if not release.test_meta:
        del splits["test"]
    truth: dict[str, list[tuple[Camera, float]]] = {}
    for split, ids in splits.items():
        meta: dict[str, Any] = {"w": width, "h": height, "k": [], "w2c": [], "fn": [], "cam_id": []}
        views = []
        for t in range(timesteps):
            row: dict[str, list[Any]] = {"k": [], "w2c": [], "fn": [], "cam_id": []}
            for c in ids:
                camera = cameras[c]
                time = _time(t, timesteps)
                fn = f"{c}/{t:06d}.jpg"
                rgba = render_rgba(SCENE, camera, time)
                rgb = render_rgb(camera, time)
                (folder / "ims" / str(c)).mkdir(parents=True, exist_ok=True)
                image = folder / "ims" / (fn.replace(".jpg", ".png") if release.png else fn)
                assert cv2.imwrite(
                    str(image), rgb[..., ::-1].copy(), [cv2.IMWRITE_JPEG_QUALITY, 98]
                )
                if seg and (release.seg_cameras is None or c in release.seg_cameras):
                    (folder / "seg" / str(c)).mkdir(parents=True, exist_ok=True)
                    labels = (rgba[..., 3] > 0.5).astype(np.uint8)  # 0/1, as the released data
                    assert cv2.imwrite(str(folder / "seg" / f"{c}/{t:06d}.png"), labels)
                k = [[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]]
                row["k"].append(k)
                row["w2c"].append(_pose_entry(camera, release))
                row["fn"].append(fn)
                row["cam_id"].append(c)
                views.append((camera, time))
            for key, values in row.items():
                meta[key].append(values)
        (folder / f"{split}_meta.json").write_text(json.dumps(meta))
        truth[split] = views
    if point_cloud:
        xyz, rgb = sample_point_cloud(SCENE, cameras[:num_train], count=600)
        if release.mirrored:
            xyz = xyz * np.array([-1.0, 1.0, 1.0])
        data = np.concatenate([xyz, rgb, np.ones((len(xyz), 1))], axis=1)
        np.savez(folder / "init_pt_cld.npz", data=data)
    return Truth(truth)


# ---------------------------------------------------------------- DyNeRF


def llff_row(camera: Camera, near: float, far: float) -> np.ndarray:
    """One poses_bounds.npy row: [down | right | back | centre | (H, W, focal)], bounds."""
    w2c = camera.world_to_camera.double().numpy()
    rotation = w2c[:3, :3]  # rows: right, down, forward in world space
    centre = -rotation.T @ w2c[:3, 3]
    right, down, forward = rotation
    matrix = np.stack(
        [down, right, -forward, centre, np.array([camera.height, camera.width, camera.fx])], axis=1
    )
    return np.concatenate([matrix.reshape(-1), [near, far]])


def write_video(path: Path, frames: list[np.ndarray], fps: int = 10) -> None:
    height, width = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"), fps, (width, height))
    assert writer.isOpened(), f"OpenCV cannot write {path}"
    for frame in frames:
        writer.write(np.ascontiguousarray(frame[..., ::-1]))
    writer.release()


def write_dynerf(
    folder: Path,
    num_cameras: int = 4,
    frames: int = 5,
    size: tuple[int, int] = (32, 32),
    short: dict[int, int] | None = None,
    point_cloud: bool = False,
) -> Truth:
    """poses_bounds.npy and cam00.mp4 … (mp4v): a forward-facing arc of square-pixel,
    centred cameras (what LLFF can express). `short` gives some cameras fewer frames."""
    folder.mkdir(parents=True, exist_ok=True)
    cameras = [
        ring_camera(math.radians(-30 + 60 * c / max(num_cameras - 1, 1)), math.radians(30), size)
        for c in range(num_cameras)
    ]
    rows = []
    for c, camera in enumerate(cameras):
        count = (short or {}).get(c, frames)
        images = [render_rgb(camera, _time(f, frames)) for f in range(count)]
        write_video(folder / f"cam{c:02d}.mp4", images)
        rows.append(llff_row(camera, 2.0, 5.5))
    np.save(folder / "poses_bounds.npy", np.stack(rows))
    if point_cloud:
        xyz, rgb = sample_point_cloud(SCENE, cameras[1:], count=600)
        color8 = np.round(rgb * 255).astype(np.uint8)
        write_ply(
            folder / "points3d.ply",
            {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "red": color8[:, 0],
             "green": color8[:, 1], "blue": color8[:, 2]},
        )  # fmt: skip
    times = [_time(f, frames) for f in range(frames)]
    return Truth(
        {
            "train": [(cameras[c], t) for t in times for c in range(1, num_cameras)],
            "test": [(cameras[0], t) for t in times],
        }
    )


# ---------------------------------------------------------------- Nerfies


@dataclass(frozen=True)
class NerfiesWorld:
    """The file's world: x_world = x_scene / scale + center, so that Nerfies'
    normalisation (x_world − center) · scale gives back the procedural scene."""

    center: tuple[float, float, float] = (0.4, -1.2, 2.0)
    scale: float = 0.25

    def to_world(self, points: np.ndarray) -> np.ndarray:
        return points / self.scale + np.asarray(self.center)


def nerfies_camera_json(
    camera: Camera, world: NerfiesWorld, ratio: float = 1.0, distortion: dict | None = None
) -> dict:
    """camera/<id>.json for a procedural camera (its fy must be fx · ratio)."""
    w2c = camera.world_to_camera.double().numpy()
    centre = -w2c[:3, :3].T @ w2c[:3, 3]
    lens = {"radial_distortion": [0.0, 0.0, 0.0], "tangential_distortion": [0.0, 0.0]}
    return {
        "orientation": w2c[:3, :3].tolist(),
        "position": world.to_world(centre).tolist(),
        "focal_length": camera.fx,
        "principal_point": [camera.cx, camera.cy],
        "skew": 0.0,
        "pixel_aspect_ratio": ratio,
        "image_size": [camera.width, camera.height],
        **lens,
        **(distortion or {}),
    }


def nerfies_project(camera: dict, points_world: np.ndarray) -> np.ndarray:
    """Nerfies' `Camera.project`, transcribed from its definition (pixel centres +0.5)."""
    local = (np.asarray(camera["orientation"]) @ (points_world - camera["position"]).T).T
    x, y = local[:, 0] / local[:, 2], local[:, 1] / local[:, 2]
    k1, k2, k3 = camera["radial_distortion"]
    p1, p2 = camera["tangential_distortion" if "tangential_distortion" in camera else "tangential"]
    r2 = x * x + y * y
    d = 1 + r2 * (k1 + r2 * (k2 + k3 * r2))
    xd = x * d + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * d + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
    f, (cx, cy) = camera["focal_length"], camera["principal_point"]
    u = f * xd + camera["skew"] * yd + cx
    v = f * camera["pixel_aspect_ratio"] * yd + cy
    return np.stack([u, v], axis=1)


def write_nerfies(
    folder: Path,
    frames: int = 10,
    size: tuple[int, int] = (32, 24),
    world: NerfiesWorld | None = None,
    val_every: int = 4,
    scales: tuple[int, ...] = (1, 2),
    points: bool = False,
) -> Truth:
    """A handheld-style capture: one camera per frame moving on an arc, time = frame.
    Cameras have pixel_aspect_ratio 1.1 and an off-centre principal point."""
    world = world or NerfiesWorld()
    width, height = size
    ratio = 1.1
    ids = [f"{i:06d}" for i in range(frames)]
    val_ids = ids[val_every - 1 :: val_every]
    train_ids = [i for i in ids if i not in val_ids]
    cameras = {}
    for index, frame_id in enumerate(ids):
        f = 0.9 * width
        camera = ring_camera(
            math.radians(-50 + 100 * index / max(frames - 1, 1)),
            math.radians(25 + 10 * math.sin(index)),
            size,
            focal=(f, f * ratio),
            principal=(width / 2 + 0.8, height / 2 - 1.1),
        )
        cameras[frame_id] = camera
        time = _time(index, frames)
        rgb = render_rgb(camera, time)
        for k in scales:
            small = (
                rgb
                if k == 1
                else cv2.resize(
                    rgb, (round(width / k), round(height / k)), interpolation=cv2.INTER_AREA
                )
            )
            _write_png(folder / "rgb" / f"{k}x" / f"{frame_id}.png", small)
        (folder / "camera").mkdir(parents=True, exist_ok=True)
        (folder / "camera" / f"{frame_id}.json").write_text(
            json.dumps(nerfies_camera_json(camera, world, ratio))
        )
    (folder / "dataset.json").write_text(
        json.dumps({"count": frames, "num_exemplars": len(train_ids), "ids": ids,
                    "train_ids": train_ids, "val_ids": val_ids})
    )  # fmt: skip
    metadata = {
        frame_id: {"warp_id": i, "appearance_id": i, "camera_id": 0}
        for i, frame_id in enumerate(ids)
    }
    (folder / "metadata.json").write_text(json.dumps(metadata))
    scene = {"center": list(world.center), "scale": world.scale, "near": 1.5, "far": 5.5}
    (folder / "scene.json").write_text(json.dumps(scene))
    if points:
        xyz, _ = sample_point_cloud(SCENE, list(cameras.values()), count=600)
        np.save(folder / "points.npy", world.to_world(xyz))
    return Truth(
        {
            "train": [(cameras[i], _time(ids.index(i), frames)) for i in train_ids],
            "test": [(cameras[i], _time(ids.index(i), frames)) for i in val_ids],
        }
    )

"""The built-in procedural dynamic scene, ray cast analytically and written as D-NeRF.

Four Lambert-shaded, textured primitives stand in a box around the origin (world z is
up, as in Blender), on a transparent background:

- `pedestal`: a static flat box (soft checker) whose top is the floor at z = −0.3;
- `pillar`: a static tall box with soft horizontal stripes;
- `ball`: a sphere with a longitude/latitude checker that orbits once around a vertical
  axis over t ∈ [0, 1] while bouncing twice;
- `cube`: a floating cube with a colour per face that turns 270° about a tilted axis
  while bobbing up and down.

Light: ambient 0.35 plus one directional light 0.65 (no shadows, so a static object
looks the same at every time). With `motion=False` every object stays at its t = 0 pose
and none is dynamic.

The images are rendered by casting rays through every pixel (2×2 supersampled, so the
silhouettes get fractional alpha), not by Gaussian splatting: the scene is ground truth
for the splatting code, independent of it. Cameras sit on an upper hemisphere
(elevation 15°–50°) at a fixed radius, looking at the origin. `points3d.ply` holds
points sampled on the surfaces at t = 0, with their shaded colours, kept only where at
least two train cameras see them (as a structure-from-motion cloud would be).

Letters: R rays, N points, H×W image.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch
from jaxtyping import Bool, Float

from dyngs.datamanagers.cameras import world_to_camera_to_blender
from dyngs.datamanagers.progress import progress_bar
from dyngs.ply import write_ply
from dyngs.types import Camera

GENERATOR_VERSION = 1
"""Part of the cache key: bump it whenever the generated images change."""

FOV_X = math.radians(45.0)
CAMERA_RADIUS = 3.5
"""Distance of every camera from the origin: the closest at which no view cuts the pedestal."""
ELEVATION_RANGE = (math.radians(15.0), math.radians(50.0))
LIGHT_DIRECTION = np.array([0.4, -0.3, 0.85]) / np.linalg.norm([0.4, -0.3, 0.85])
"""Unit vector towards the light."""
AMBIENT, DIFFUSE = 0.35, 0.65
SUPERSAMPLE = 2
"""Rays per pixel along each axis."""
NUM_CLOUD_SAMPLES = 4000
"""Surface samples drawn for points3d.ply before the visibility test (~3k survive)."""
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


@dataclass(frozen=True)
class ProceduralSceneConfig:
    """The built-in synthetic dynamic scene (see `dyngs.datamanagers.procedural`)."""

    resolution: int = 128
    """Image width and height in pixels."""
    num_times: int = 40
    """Train timestamps, evenly spaced over [0, 1]."""
    views_per_time: int = 2
    """Train cameras per timestamp, at different azimuths (a multi-view capture)."""
    num_test: int = 20
    """Test views: novel cameras at times halfway between train times."""
    num_val: int = 10
    """Validation views, drawn like the test views (0: the parser falls back to test)."""
    motion: bool = True
    """False: every object stays at its t = 0 pose (a static scene seen over time)."""
    motion_start: float = 0.0
    """Time until which every object holds its t = 0 pose; from it to t = 1 the moving
    objects go through their whole motion, faster (a capture that starts before the
    action: what has not moved yet is not necessarily static)."""
    fixed_cameras: int = 0
    """> 0: the train views come from this many cameras that never move, each seeing every
    timestamp (a multi-view rig, like Panoptic or DyNeRF); 0: `views_per_time` cameras at
    new places at each timestamp (like D-NeRF)."""
    seed: int = 0
    """Seeds the camera jitter and the point-cloud sampling."""

    def __post_init__(self) -> None:
        if self.resolution < 8:
            raise ValueError(f"resolution must be ≥ 8, got {self.resolution}")
        if self.num_times < 1 or self.views_per_time < 1 or self.num_test < 1:
            raise ValueError("num_times, views_per_time and num_test must be ≥ 1")
        if not 0.0 <= self.motion_start < 1.0:
            raise ValueError(f"motion_start must be in [0, 1), got {self.motion_start}")
        if self.num_val < 0:
            raise ValueError(f"num_val must be ≥ 0, got {self.num_val}")
        if self.fixed_cameras < 0:
            raise ValueError(f"fixed_cameras must be ≥ 0, got {self.fixed_cameras}")


@dataclass(frozen=True)
class Texture:
    """A smooth procedural pattern blending two colours (or six face colours)."""

    pattern: Literal["checker", "stripes", "globe", "faces"]
    colors: tuple[tuple[float, float, float], ...]
    period: float = 0.25
    """Cell size (checker) or wavelength (stripes) in object-local units."""


@dataclass(frozen=True, eq=False)
class SceneObject:
    """One primitive at one time: a box (half-extents `size`) or a sphere (radius size[0])."""

    name: str
    kind: Literal["box", "sphere"]
    center: Float[np.ndarray, " 3"]
    rotation: Float[np.ndarray, "3 3"]
    """Object-to-world rotation: world = rotation @ local + center."""
    size: Float[np.ndarray, " 3"]
    dynamic: bool
    """Whether the object moves over time (False for all objects when motion is off)."""
    texture: Texture = field(repr=False)

    def to_local(self, points: Float[np.ndarray, "N 3"]) -> Float[np.ndarray, "N 3"]:
        return (points - self.center) @ self.rotation

    def signed_distance(self, points: Float[np.ndarray, "N 3"]) -> Float[np.ndarray, " N"]:
        """Exact signed distance to the surface (negative inside)."""
        local = self.to_local(points)
        if self.kind == "sphere":
            return np.linalg.norm(local, axis=1) - self.size[0]
        q = np.abs(local) - self.size
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        return outside + np.minimum(q.max(axis=1), 0.0)

    def intersect(
        self, origins: Float[np.ndarray, "R 3"], directions: Float[np.ndarray, "R 3"]
    ) -> tuple[Float[np.ndarray, " R"], Float[np.ndarray, "R 3"]]:
        """Distance along each (unit) ray to the first entry into the object (inf on a
        miss, or when the ray starts inside) and the local-frame normal there."""
        o = self.to_local(origins)
        d = directions @ self.rotation
        if self.kind == "sphere":
            b = (o * d).sum(1)
            c = (o * o).sum(1) - self.size[0] ** 2
            disc = b * b - c
            s = -b - np.sqrt(np.maximum(disc, 0.0))
            s = np.where((disc >= 0) & (s > 0), s, np.inf)
            hit = np.isfinite(s)
            normals = np.zeros_like(o)
            normals[hit] = (o[hit] + s[hit, None] * d[hit]) / self.size[0]
            return s, normals
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-self.size - o) / d
            t2 = (self.size - o) / d
        # Slab test. 0/0 (a ray inside a face's plane) gives NaN: treat that slab as open.
        near = np.minimum(t1, t2)
        far = np.maximum(t1, t2)
        near[np.isnan(near)] = -np.inf
        far[np.isnan(far)] = np.inf
        entry, exit_ = near.max(axis=1), far.min(axis=1)
        s = np.where((entry <= exit_) & (entry > 0), entry, np.inf)
        axis = near.argmax(axis=1)
        normals = np.zeros_like(o)
        rows = np.arange(len(o))
        normals[rows, axis] = -np.sign(d[rows, axis])
        return s, normals

    def albedo(
        self, local_points: Float[np.ndarray, "N 3"], local_normals: Float[np.ndarray, "N 3"]
    ) -> Float[np.ndarray, "N 3"]:
        """Surface colour in [0, 1] at points on the surface (object-local frame)."""
        tex = self.texture
        colors = np.asarray(tex.colors, dtype=np.float64)
        if tex.pattern == "faces":
            axis = np.abs(local_normals).argmax(axis=1)
            positive = local_normals[np.arange(len(axis)), axis] > 0
            base = colors[2 * axis + positive.astype(np.int64)]
            wave = np.prod(np.sin(np.pi * local_points / tex.period), axis=1)
            return base * (0.75 + 0.25 * np.clip(0.5 + 3.0 * wave, 0.0, 1.0))[:, None]
        if tex.pattern == "checker":
            wave = np.prod(np.sin(np.pi * local_points / tex.period), axis=1)
            weight = np.clip(0.5 + 3.0 * wave, 0.0, 1.0)
        elif tex.pattern == "stripes":
            weight = np.clip(0.5 + 2.0 * np.sin(2 * np.pi * local_points[:, 2] / tex.period), 0, 1)
        else:  # globe: 8 longitude × 4 latitude cells
            unit = local_points / np.linalg.norm(local_points, axis=1, keepdims=True)
            longitude = np.arctan2(unit[:, 1], unit[:, 0])
            latitude = np.arcsin(np.clip(unit[:, 2], -1.0, 1.0))
            weight = np.clip(0.5 + 3.0 * np.sin(4 * longitude) * np.sin(4 * latitude), 0, 1)
        return colors[0] * (1 - weight[:, None]) + colors[1] * weight[:, None]

    def shade(
        self, local_points: Float[np.ndarray, "N 3"], local_normals: Float[np.ndarray, "N 3"]
    ) -> Float[np.ndarray, "N 3"]:
        """Lambert colour: albedo · (ambient + diffuse · max(0, n·l))."""
        normals = local_normals @ self.rotation.T
        light = AMBIENT + DIFFUSE * np.maximum(normals @ LIGHT_DIRECTION, 0.0)
        return self.albedo(local_points, local_normals) * light[:, None]


def _rotation(axis: tuple[float, float, float], angle: float) -> Float[np.ndarray, "3 3"]:
    """Rodrigues' formula."""
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


def _still_objects() -> list[SceneObject]:
    """The primitives that never move: a pedestal and a pillar."""
    return [
        SceneObject(
            "pedestal",
            "box",
            np.array([0.0, 0.0, -0.4]),
            np.eye(3),
            np.array([0.85, 0.85, 0.1]),
            dynamic=False,
            texture=Texture("checker", ((0.82, 0.76, 0.64), (0.30, 0.42, 0.62)), 0.25),
        ),
        SceneObject(
            "pillar",
            "box",
            np.array([-0.5, -0.5, 0.0]),
            _rotation((0.0, 0.0, 1.0), 0.4),
            np.array([0.12, 0.12, 0.3]),
            dynamic=False,
            texture=Texture("stripes", ((0.86, 0.24, 0.18), (0.96, 0.92, 0.82)), 0.15),
        ),
    ]


def scene_objects(config: ProceduralSceneConfig, t: float) -> list[SceneObject]:
    """The scene's primitives at time t ∈ [0, 1]."""
    moving = config.motion
    start = config.motion_start
    t = max(0.0, (t - start) / (1.0 - start)) if moving else 0.0
    phase = 2 * math.pi * t
    ball_center = np.array(
        [
            0.15 + 0.35 * math.cos(phase),
            0.2 + 0.35 * math.sin(phase),
            -0.12 + 0.3 * math.sin(phase) ** 2,
        ]
    )
    cube_center = np.array([0.55, -0.5, 0.1 + 0.12 * math.sin(phase)])
    cube_rotation = _rotation((0.3, 0.2, 1.0), 0.5 + 1.5 * math.pi * t)
    return [
        *_still_objects(),
        SceneObject(
            "ball",
            "sphere",
            ball_center,
            np.eye(3),
            np.full(3, 0.18),
            dynamic=moving,
            texture=Texture("globe", ((0.16, 0.55, 0.28), (0.96, 0.84, 0.28))),
        ),
        SceneObject(
            "cube",
            "box",
            cube_center,
            cube_rotation,
            np.full(3, 0.15),
            dynamic=moving,
            texture=Texture(
                "faces",
                (
                    (0.90, 0.30, 0.25),
                    (0.95, 0.60, 0.20),
                    (0.25, 0.70, 0.35),
                    (0.20, 0.65, 0.80),
                    (0.55, 0.35, 0.80),
                    (0.95, 0.90, 0.85),
                ),
                0.1,
            ),
        ),
    ]


def is_on_dynamic_object(
    points: Float[np.ndarray, "N 3"], t: float, config: ProceduralSceneConfig, tol: float = 0.02
) -> Bool[np.ndarray, " N"]:
    """Whether each point lies on or inside (within `tol` of) an object that moves."""
    points = np.asarray(points, dtype=np.float64)
    result = np.zeros(len(points), dtype=bool)
    for obj in scene_objects(config, t):
        if obj.dynamic:
            result |= obj.signed_distance(points) <= tol
    return result


def cast(
    objects: list[SceneObject],
    origins: Float[np.ndarray, "R 3"] | Float[np.ndarray, " 3"],
    directions: Float[np.ndarray, "R 3"],
) -> tuple[Float[np.ndarray, " R"], Float[np.ndarray, "R 3"]]:
    """Distance to the nearest surface along each unit ray (inf on a miss) and its shaded
    colour. `origins` may be one point shared by all rays (a pinhole camera)."""
    best = np.full(len(directions), np.inf)
    color = np.zeros((len(directions), 3))
    shared = origins.ndim == 1
    for obj in objects:
        # Only rays passing within the object's bounding sphere can hit it: testing that
        # first (one dot product per ray) makes small objects nearly free.
        radius = float(np.linalg.norm(obj.size)) if obj.kind == "box" else float(obj.size[0])
        offset = origins - obj.center
        if shared:
            along = directions @ offset
            squared = float(offset @ offset)
        else:
            along = np.einsum("ij,ij->i", offset, directions)
            squared = np.einsum("ij,ij->i", offset, offset)
        rays = np.flatnonzero((squared - along * along <= radius * radius) & (along < radius))
        if len(rays) == 0:
            continue
        starts = np.broadcast_to(origins, (len(rays), 3)) if shared else origins[rays]
        s, normals = obj.intersect(starts, directions[rays])
        closer = s < best[rays]
        rays, s, normals, starts = rays[closer], s[closer], normals[closer], starts[closer]
        best[rays] = s
        local = obj.to_local(starts + s[:, None] * directions[rays])
        color[rays] = obj.shade(local, normals)
    return best, color


def render_rgba(
    config: ProceduralSceneConfig, camera: Camera, t: float
) -> Float[np.ndarray, "H W 4"]:
    """Straight-alpha RGBA in [0, 1] of the scene at time t (2×2 supersampled)."""
    n = SUPERSAMPLE
    offsets = (np.arange(n) + 0.5) / n  # sub-pixel positions; pixel centres sit at +0.5
    x = ((np.arange(camera.width)[:, None] + offsets).reshape(-1) - camera.cx) / camera.fx
    y = ((np.arange(camera.height)[:, None] + offsets).reshape(-1) - camera.cy) / camera.fy
    w2c = camera.world_to_camera.double().cpu().numpy()
    rotation = w2c[:3, :3]
    # World direction of camera ray (x, y, 1) is Rᵀ(x, y, 1); R's rows are orthonormal,
    # so its length is that of (x, y, 1).
    inverse_length = 1.0 / np.sqrt(x[None, :] ** 2 + y[:, None] ** 2 + 1.0)
    directions = (
        x[None, :, None] * rotation[0] + y[:, None, None] * rotation[1] + rotation[2]
    ) * inverse_length[..., None]
    eye = -rotation.T @ w2c[:3, 3]
    distance, color = cast(scene_objects(config, t), eye, directions.reshape(-1, 3))
    shape = (camera.height, n, camera.width, n)
    alpha = np.isfinite(distance).reshape(shape).mean(axis=(1, 3))
    premultiplied = color.reshape(*shape, 3).mean(axis=(1, 3))  # misses are black
    rgb = premultiplied / np.maximum(alpha, 1e-12)[..., None]
    return np.concatenate([np.clip(rgb, 0.0, 1.0), alpha[..., None]], axis=-1)


def look_at(eye: Float[np.ndarray, " 3"]) -> Float[np.ndarray, "4 4"]:
    """OpenCV world-to-camera for a camera at `eye` looking at the origin, world z up."""
    forward = -eye / np.linalg.norm(eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    w2c = np.eye(4)
    w2c[:3, :3] = rotation
    w2c[:3, 3] = -rotation @ eye
    return w2c


def _camera_at(config: ProceduralSceneConfig, azimuth: float, elevation: float) -> Camera:
    eye = CAMERA_RADIUS * np.array(
        [
            math.cos(elevation) * math.cos(azimuth),
            math.cos(elevation) * math.sin(azimuth),
            math.sin(elevation),
        ]
    )
    w2c = torch.from_numpy(look_at(eye)).float()
    return Camera.from_fov(FOV_X, config.resolution, config.resolution, w2c)


def capture(config: ProceduralSceneConfig) -> dict[str, list[tuple[Camera, float]]]:
    """(camera, time) of every view, per split.

    Train: `views_per_time` cameras per timestamp, spread around the circle (golden-angle
    steps between timestamps) with a little seeded jitter; or, with `fixed_cameras`, the
    same ring of cameras at every timestamp. Val and test: novel cameras at
    times halfway between two train timestamps.
    """
    rng = np.random.default_rng(config.seed)
    lo, hi = ELEVATION_RANGE
    train: list[tuple[Camera, float]] = []
    steps = max(config.num_times - 1, 1)
    rig = [
        _camera_at(
            config, 2 * math.pi * (j + 0.5) / config.fixed_cameras, lo + (hi - lo) * (j % 3) / 2
        )
        for j in range(config.fixed_cameras)
    ]
    for k in range(config.num_times):
        t = k / steps if config.num_times > 1 else 0.0
        if rig:
            train += [(camera, t) for camera in rig]
            continue
        for view in range(config.views_per_time):
            azimuth = 2 * math.pi * ((k * _GOLDEN) % 1.0 + view / config.views_per_time)
            azimuth += rng.uniform(-0.15, 0.15)
            elevation = lo + (hi - lo) * ((k * 0.7548776662 + view * 0.5) % 1.0)
            train.append((_camera_at(config, azimuth, elevation), t))
    splits = {"train": train}
    for name, count, shift in (("val", config.num_val, 0.25), ("test", config.num_test, 0.75)):
        views: list[tuple[Camera, float]] = []
        for j in range(count):
            interval = min(int((j + 0.5) * steps / count), steps - 1)
            t = (interval + 0.5) / steps if config.num_times > 1 else 0.0
            azimuth = 2 * math.pi * ((j * _GOLDEN + shift / count) % 1.0) + rng.uniform(-0.1, 0.1)
            elevation = rng.uniform(lo, hi)
            views.append((_camera_at(config, azimuth, elevation), t))
        splits[name] = views
    return splits


def sample_point_cloud(
    config: ProceduralSceneConfig, cameras: list[Camera], count: int = NUM_CLOUD_SAMPLES
) -> tuple[Float[np.ndarray, "N 3"], Float[np.ndarray, "N 3"]]:
    """Points on the surfaces at t = 0 seen (front-facing, unoccluded) by ≥ 2 cameras,
    with their shaded colours in [0, 1]."""
    rng = np.random.default_rng(config.seed + 1)
    objects = scene_objects(config, 0.0)
    areas = []
    for obj in objects:
        if obj.kind == "sphere":
            areas.append(4 * math.pi * obj.size[0] ** 2)
        else:
            a, b, c = obj.size
            areas.append(8 * (a * b + b * c + a * c))
    counts = rng.multinomial(count, np.asarray(areas) / sum(areas))
    points, colors, normals = [], [], []
    for obj, n in zip(objects, counts, strict=True):
        if obj.kind == "sphere":
            local_n = rng.normal(size=(n, 3))
            local_n /= np.linalg.norm(local_n, axis=1, keepdims=True)
            local = local_n * obj.size[0]
        else:
            a, b, c = obj.size
            face_areas = np.array([b * c, b * c, a * c, a * c, a * b, a * b])
            faces = rng.choice(6, size=n, p=face_areas / face_areas.sum())
            axis, sign = faces // 2, np.where(faces % 2 == 1, 1.0, -1.0)
            local = rng.uniform(-1.0, 1.0, size=(n, 3)) * obj.size
            local[np.arange(n), axis] = sign * obj.size[axis]
            local_n = np.zeros((n, 3))
            local_n[np.arange(n), axis] = sign
        points.append(local @ obj.rotation.T + obj.center)
        normals.append(local_n @ obj.rotation.T)
        colors.append(obj.shade(local, local_n))
    xyz, rgb, nrm = np.concatenate(points), np.concatenate(colors), np.concatenate(normals)

    start = xyz + 1e-4 * nrm
    inside = np.zeros(len(xyz), dtype=bool)
    for obj in objects:
        inside |= obj.signed_distance(start) < 0
    seen = np.zeros(len(xyz), dtype=np.int64)
    for camera in cameras:
        eye = camera.center.double().cpu().numpy()
        to_eye = eye - start
        distance = np.linalg.norm(to_eye, axis=1)
        direction = to_eye / distance[:, None]
        facing = (nrm * direction).sum(1) > 0
        blocked, _ = cast(objects, start, direction)
        seen += facing & (blocked >= distance)
    keep = (seen >= 2) & ~inside
    return xyz[keep], rgb[keep]


def write_procedural_scene(folder: Path, config: ProceduralSceneConfig) -> None:
    """Render the scene into `folder` in D-NeRF format (RGBA PNGs, transforms_*.json,
    points3d.ply). The folder is created if needed; existing files are overwritten."""
    folder = Path(folder)
    views = capture(config)
    total = sum(len(v) for v in views.values())
    with progress_bar() as progress:
        task = progress.add_task("rendering the demo scene", total=total)
        for split, split_views in views.items():
            if not split_views:
                continue
            (folder / split).mkdir(parents=True, exist_ok=True)
            frames = []
            for index, (camera, t) in enumerate(split_views):
                rgba = render_rgba(config, camera, t)
                image = np.round(rgba * 255.0).astype(np.uint8)
                name = f"r_{index:03d}"
                if not cv2.imwrite(str(folder / split / f"{name}.png"), image[..., [2, 1, 0, 3]]):
                    raise OSError(f"{folder / split / name}.png: cannot write image")
                c2w = world_to_camera_to_blender(camera.world_to_camera.double().numpy())
                frames.append(
                    {"file_path": f"./{split}/{name}", "time": t, "transform_matrix": c2w.tolist()}
                )
                progress.advance(task)
            meta = {"camera_angle_x": FOV_X, "frames": frames}
            (folder / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))
    xyz, rgb = sample_point_cloud(config, [camera for camera, _ in views["train"]])
    color8 = np.round(rgb * 255.0).astype(np.uint8)
    write_ply(
        folder / "points3d.ply",
        {
            "x": xyz[:, 0],
            "y": xyz[:, 1],
            "z": xyz[:, 2],
            "red": color8[:, 0],
            "green": color8[:, 1],
            "blue": color8[:, 2],
        },
    )


def cache_dir() -> Path:
    """$DYNGS_CACHE, else ~/.cache/dyngs."""
    return Path(os.environ.get("DYNGS_CACHE") or Path.home() / ".cache" / "dyngs")


ADDED_FIELDS = ("motion_start",)
"""Config fields added after the first version: each counts in `config_key` only where it
is not its default, so that adding one leaves the scenes already in the cache where they
are."""


def config_key(config: ProceduralSceneConfig) -> str:
    """A short hash of the config and the generator version (see `ADDED_FIELDS`)."""
    default = ProceduralSceneConfig()
    fields = {
        name: value
        for name, value in asdict(config).items()
        if name not in ADDED_FIELDS or value != getattr(default, name)
    }
    text = json.dumps({"version": GENERATOR_VERSION, **fields}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:10]


def demo_path(config: ProceduralSceneConfig | None = None) -> Path:
    """The demo scene's folder in the cache, rendered there on first use.

    Rendering goes to a temporary folder beside it that is renamed into place at the
    end, so an interrupted run never leaves a half-written scene behind (and two runs
    racing each other both end up with a complete one).
    """
    config = config if config is not None else ProceduralSceneConfig()
    root = cache_dir()
    final = root / f"demo-{config_key(config)}"
    if (final / "transforms_train.json").is_file():
        return final
    root.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{final.name}-", dir=root))
    try:
        write_procedural_scene(staging, config)
        staging.chmod(0o755)
        try:
            staging.rename(final)
        except OSError:
            if not (final / "transforms_train.json").is_file():
                raise
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    return final

"""Initial points from the data: where a capture's Gaussians start.

Gaussians started where nothing is waste the first thousand steps (most are pruned,
and a few hundred may be all that is left); started on the scene, they are a picture of
it from the first step. `choose_initial_points` decides, and says in one line what it
chose:

1. A point cloud that came with the capture is used when it is real. One that is noise
   is replaced, and the run says so. A cloud is noise when its points are spread like
   uniform random points (Clark and Evans's aggregation index R ≥ 0.85: a surface
   sample scores well below it, points uniform in a box about 1; `aggregation_index`),
   or, where the images carry silhouettes of everything there is, when its points mostly
   project outside them (`silhouette_agreement`).
2. Else points are made from the images, from whatever the capture offers:
   - **carving** (`carve`): a point is kept where it projects inside the silhouette in
     (nearly) every view that sees it, the visual hull of Laurentini (1994). Views are
     carved in short windows of time (`windows`), and the hulls of all windows pooled:
     the union over time of what moves, since a monocular sequence sees each instant
     once. Silhouettes are, in order of preference, the images' alpha (everything
     there is), the pixels unlike the background colour in synthetic scenes that have
     one, or a segmentation (a foreground only);
   - **what moves**, on captures with fixed cameras: pixels far from their camera's
     temporal median, carved the same way, so that small moving objects (a few pixels
     of thousands) get points of their own;
   - **triangulation** (`triangulate`) where there are no silhouettes of everything,
     or only of a foreground: SIFT features (Lowe 2004) matched between views of
     different viewpoints, kept where they agree with the known epipolar geometry, and
     triangulated with the known poses, COLMAP's point triangulation with the poses
     given.
   Points take the median colour of the pixels they project to.
3. Random points (the parser's: in the box, or in the cameras' common view) only when
   nothing better can be made, and the run says so.

Letters: V views, H×W image, P points, C candidates.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from jaxtyping import Bool, Float
from torch import Tensor

from dyngs.datamanagers.base import SceneData, Split
from dyngs.datamanagers.cameras import scene_box_from_cameras
from dyngs.datamanagers.fixed_cameras import FixedCameras, dilate
from dyngs.neighbors import knn
from dyngs.types import Camera, SceneBox

NOISE_AGGREGATION = 0.85
"""Clark–Evans R at or above which a point cloud is spread like noise. Measured: points
uniform in a cube score 1.04-1.11 (the box's edges lengthen distances), a Gaussian blob
0.97-1.00, at 300 to 100 000 points; samples of the procedural scene's surfaces 0.45 at
2 575 points rising to 0.74 at 188 (sparser samples look more like a volume). R's
standard error at 300 points is about 0.015."""

NOISE_AGREEMENT = 0.6
"""A cloud whose points lie inside the silhouettes of fewer than this share of the views
that see them (on average) is not of this scene."""

WINDOW_VIEWS = 8
"""A carving window holds at least this many views (and at least `WINDOW_VIEWPOINTS`
distinct viewpoints where the capture has them): enough cones to close a hull."""

WINDOW_VIEWPOINTS = 4

MAX_WINDOWS = 16
"""At most this many windows are carved, spread evenly over the sequence."""

FIRST_WINDOW_SHARE = 0.5
"""Share of the carved points from the earliest window: the canonical Gaussians are fitted
to the start of the sequence first (the warm-up)."""

BACKGROUND_TOLERANCE = 4 / 255
"""A pixel within this of the background colour, in every channel, is background."""

BACKGROUND_SHARE = 0.1
"""Images whose background colour covers at least this share of their pixels have
silhouettes by that colour (synthetic renders on a plain background)."""


@dataclass
class Silhouettes:
    """Per training view, where something is (True), or None for a view without one."""

    masks: list[Bool[Tensor, "H W"] | None]
    kind: str
    """What they mark: "alpha" or "background colour" (everything there is, so outside
    is empty space), "segmentation" (a foreground) or "motion" (what moves)."""

    @property
    def everything(self) -> bool:
        """Whether outside a silhouette is empty space (so that carving finds all there is)."""
        return self.kind in ("alpha", "background colour")

    def count(self) -> int:
        return sum(mask is not None for mask in self.masks)


@dataclass
class Points:
    points: Float[Tensor, "P 3"]
    colors: Float[Tensor, "P 3"] | None
    source: str
    lifetimes: Float[Tensor, "P 2"] | None = None
    """(τ, σ) per point; σ = inf for points that exist at every time."""


def _image(split: Split, index: int) -> Float[Tensor, "H W 3"]:
    return split.images[index].float() / 255.0


def silhouettes(split: Split, background: Float[Tensor, " 3"]) -> Silhouettes | None:
    """The split's silhouettes of what there is: its masks (alpha or segmentation), else
    the pixels unlike the background colour where most images show it widely."""
    if split.masks is not None:
        masks = [
            split.masks[i][..., 0] > 127 if split.has_mask(i) else None for i in range(len(split))
        ]
        return Silhouettes(masks, split.mask_kind)
    step = max(1, len(split) // 16)
    samples = [_image(split, i) for i in range(0, len(split), step)]
    plain = [float(_is_background(image, background).float().mean()) for image in samples]
    if sorted(plain)[len(plain) // 2] < BACKGROUND_SHARE:
        return None
    masks = [~_is_background(_image(split, i), background) for i in range(len(split))]
    return Silhouettes(list(masks), "background colour")


def _is_background(image: Float[Tensor, "H W 3"], background: Tensor) -> Bool[Tensor, "H W"]:
    return ((image - background.to(image.dtype)).abs() <= BACKGROUND_TOLERANCE).all(-1)


def moving_silhouettes(split: Split, pixel_change: float) -> Silhouettes | None:
    """On fixed cameras, each view's pixels far from its camera's temporal median (what is
    not usually there: what moves); None without fixed cameras or where nothing moves."""
    fixed = FixedCameras.of(split)
    if fixed is None:
        return None
    masks: list[Tensor | None] = []
    for i in range(len(split)):
        changed = fixed.changed(i, _image(split, i), pixel_change)
        masks.append(changed if changed is not None and bool(changed.any()) else None)
    found = Silhouettes(masks, "motion")
    return found if found.count() >= WINDOW_VIEWS else None


# ---------------------------------------------------------------------------------------
# Judging a given cloud


def aggregation_index(points: Float[Tensor, "P 3"], sample: int = 4000, seed: int = 0) -> float:
    """Clark and Evans's (1954) R: the mean distance from a point to its nearest neighbour
    over that expected of as many points uniform in the same volume (the 1st–99th
    percentile box), Γ(4/3) (3 / (4π λ))^(1/3) in three dimensions. About 1 for uniform
    noise, well under 1 for points on surfaces. Estimated on a random `sample`."""
    if len(points) > sample:
        keep = torch.randperm(len(points), generator=torch.Generator().manual_seed(seed))
        points = points[keep[:sample]]
    points = points.double()
    if len(points) < 10:
        return 0.0
    lower = torch.quantile(points, 0.01, dim=0)
    upper = torch.quantile(points, 0.99, dim=0)
    volume = float((upper - lower).clamp_min(1e-12).prod())
    nearest = knn(points, 1)[:, 0]
    observed = float((points - points[nearest]).norm(dim=-1).mean())
    expected = math.gamma(4 / 3) * (3 * volume / (4 * math.pi * len(points))) ** (1 / 3)
    return observed / expected


def silhouette_agreement(
    points: Float[Tensor, "P 3"], split: Split, shapes: Silhouettes, sample: int = 2000
) -> float:
    """The mean over points (a random `sample`) of the share of views with a silhouette
    that see a point and see it inside."""
    if len(points) > sample:
        points = points[
            torch.randperm(len(points), generator=torch.Generator().manual_seed(0))[:sample]
        ]
    seen = torch.zeros(len(points))
    inside = torch.zeros(len(points))
    for camera, mask in zip(split.cameras, shapes.masks, strict=True):
        if mask is None:
            continue
        hit, visible = _inside(points.double(), camera, mask)
        seen += visible.float()
        inside += hit.float()
    used = seen > 0
    return float((inside[used] / seen[used]).mean()) if bool(used.any()) else 0.0


def _inside(
    points: Float[Tensor, "P 3"], camera: Camera, mask: Bool[Tensor, "H W"]
) -> tuple[Bool[Tensor, " P"], Bool[Tensor, " P"]]:
    """Whether each point projects inside `mask` (dilated by a pixel), and whether the
    camera sees it at all (in front of it and inside the image)."""
    w2c = camera.world_to_camera.double()
    local = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = local[:, 2]
    front = z > camera.near
    z = torch.where(front, z, 1.0)
    u = (camera.fx * local[:, 0] / z + camera.cx).floor()
    v = (camera.fy * local[:, 1] / z + camera.cy).floor()
    visible = front & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    ui = u.clamp(0, camera.width - 1).long()
    vi = v.clamp(0, camera.height - 1).long()
    grown = dilate(mask.float()) > 0
    return visible & grown[vi, ui], visible


# ---------------------------------------------------------------------------------------
# Carving


def windows(split: Split, views: list[int]) -> list[list[int]]:
    """`views` in time order, cut into consecutive windows of at least `WINDOW_VIEWS`
    views and `WINDOW_VIEWPOINTS` viewpoints (fewer only where the capture has fewer), a
    timestep never split; at most `MAX_WINDOWS`, spread over the sequence, the first
    always among them."""
    order = sorted(views, key=lambda i: float(split.times[i]))
    total = len({split.cameras[i].viewpoint() for i in order})
    need_views, need_points = min(WINDOW_VIEWS, len(order)), min(WINDOW_VIEWPOINTS, total)
    found: list[list[int]] = []
    current: list[int] = []
    for position, index in enumerate(order):
        current.append(index)
        boundary = position + 1 == len(order) or float(split.times[order[position + 1]]) != float(
            split.times[index]
        )
        viewpoints = len({split.cameras[i].viewpoint() for i in current})
        if boundary and len(current) >= need_views and viewpoints >= need_points:
            found.append(current)
            current = []
    if current:  # a short tail joins the last window
        if found:
            found[-1] += current
        else:
            found.append(current)
    if len(found) > MAX_WINDOWS:
        picks = np.linspace(0, len(found) - 1, MAX_WINDOWS).round().astype(int)
        found = [found[i] for i in sorted(set(picks.tolist()))]
    return found


def _rays_into_box(
    camera: Camera, pixels: Float[Tensor, "C 2"], box: SceneBox, generator: torch.Generator
) -> Float[Tensor, "C 3"]:
    """One point per pixel, uniform in depth along its ray inside the box (rays that miss
    the box give points at its nearest face, which later tests reject)."""
    w2c = camera.world_to_camera.double()
    rotation = w2c[:3, :3]
    centre = -rotation.T @ w2c[:3, 3]
    local = torch.stack(
        ((pixels[:, 0] - camera.cx) / camera.fx, (pixels[:, 1] - camera.cy) / camera.fy,
         torch.ones(len(pixels), dtype=torch.float64)), dim=-1,
    )  # fmt: skip
    directions = local @ rotation  # = (Rᵀ local) per row: world-space rays
    lower = torch.tensor(box.lower, dtype=torch.float64)
    upper = torch.tensor(box.upper, dtype=torch.float64)
    tiny = torch.where(directions >= 0, 1e-12, -1e-12)
    inverse = 1.0 / torch.where(directions.abs() < 1e-12, tiny, directions)
    t0 = (lower - centre) * inverse
    t1 = (upper - centre) * inverse
    near = torch.minimum(t0, t1).amax(-1).clamp_min(camera.near)
    far = torch.maximum(t0, t1).amin(-1).clamp_min(near)
    depth = near + (far - near) * torch.rand(len(pixels), generator=generator, dtype=torch.float64)
    return centre + directions * depth[:, None]


def _hull_test(
    candidates: Float[Tensor, "C 3"], split: Split, views: list[int], shapes: Silhouettes
) -> tuple[Bool[Tensor, " C"], Bool[Tensor, " C"]]:
    """Which candidates lie in the hull of `views` (each has a silhouette): the viewpoints
    that see them, at least two, see them inside a silhouette, all of them but one in
    five. A viewpoint's views at several times count once, inside where any of them is:
    the union over time of what moves. Also which candidates two viewpoints see at all."""
    groups: dict[tuple[float, ...], list[int]] = {}
    for i in views:
        groups.setdefault(split.cameras[i].viewpoint(), []).append(i)
    seen = torch.zeros(len(candidates), dtype=torch.long)
    inside = torch.zeros(len(candidates), dtype=torch.long)
    for members in groups.values():
        hit = torch.zeros(len(candidates), dtype=torch.bool)
        visible = torch.zeros(len(candidates), dtype=torch.bool)
        for i in members:
            h, v = _inside(candidates, split.cameras[i], shapes.masks[i])  # type: ignore[arg-type]
            hit |= h
            visible |= v
        seen += visible.long()
        inside += hit.long()
    looked = seen >= 2
    return looked & (inside >= seen - seen // 5), looked


def _carve_window(
    split: Split,
    window: list[int],
    shapes: Silhouettes,
    box: SceneBox,
    want: int,
    generator: torch.Generator,
) -> Float[Tensor, "P 3"]:
    """Points of one window's hull (`_hull_test`): candidates along rays through each of
    its silhouettes in turn."""
    views = [i for i in window if shapes.masks[i] is not None]
    if len({split.cameras[i].viewpoint() for i in views}) < 2:
        return torch.zeros(0, 3, dtype=torch.float64)
    kept: list[Tensor] = []
    found = 0
    for attempt in range(4 * len(views)):
        if found >= want:
            break
        mask = shapes.masks[views[attempt % len(views)]]
        assert mask is not None
        rows, cols = mask.nonzero(as_tuple=True)
        if len(rows) == 0:
            continue
        picks = torch.randint(len(rows), (max(4 * want, 2048),), generator=generator)
        jitter = torch.rand(len(picks), 2, generator=generator, dtype=torch.float64)
        pixels = torch.stack((cols[picks], rows[picks]), -1).double() + jitter
        camera = split.cameras[views[attempt % len(views)]]
        candidates = _rays_into_box(camera, pixels, box, generator)
        held, _ = _hull_test(candidates, split, views, shapes)
        kept.append(candidates[held])
        found += int(held.sum())
    points = torch.cat(kept) if kept else torch.zeros(0, 3, dtype=torch.float64)
    return points[:want]


def carve(
    split: Split, shapes: Silhouettes, box: SceneBox, count: int, seed: int
) -> Float[Tensor, "P 3"]:
    """About `count` points in the pooled hulls of the split's windows (see the module
    docstring): `FIRST_WINDOW_SHARE` of them from the earliest window, the rest evenly
    from all."""
    generator = torch.Generator().manual_seed(seed)
    views = [i for i in range(len(split)) if shapes.masks[i] is not None]
    spans = windows(split, views)
    if not spans:
        return torch.zeros(0, 3)
    wants = [round(count * (1 - FIRST_WINDOW_SHARE) / len(spans))] * len(spans)
    wants[0] += round(count * FIRST_WINDOW_SHARE)
    parts = [
        _carve_window(split, span, shapes, box, want, generator)
        for span, want in zip(spans, wants, strict=True)
        if want > 0
    ]
    return torch.cat(parts).float()


def colours(
    points: Float[Tensor, "P 3"], split: Split, shapes: Silhouettes | None, views: int = 24
) -> Float[Tensor, "P 3"]:
    """Each point's median colour over the pixels it projects to, in up to `views` views
    spread over the split (inside their silhouettes, where they have them)."""
    picks = np.linspace(0, len(split) - 1, min(views, len(split))).round().astype(int)
    samples, valid = [], []
    for i in sorted(set(picks.tolist())):
        camera = split.cameras[i]
        mask = None if shapes is None else shapes.masks[i]
        full = torch.ones(camera.height, camera.width, dtype=torch.bool)
        hit, visible = _inside(points.double(), camera, mask if mask is not None else full)
        w2c = camera.world_to_camera.double()
        local = points.double() @ w2c[:3, :3].T + w2c[:3, 3]
        z = local[:, 2].clamp_min(camera.near)
        u = (camera.fx * local[:, 0] / z + camera.cx).floor().clamp(0, camera.width - 1).long()
        v = (camera.fy * local[:, 1] / z + camera.cy).floor().clamp(0, camera.height - 1).long()
        samples.append(_image(split, i)[v, u])
        valid.append(hit & visible)
    stack = torch.stack(samples)  # [V, P, 3]
    ok = torch.stack(valid)  # [V, P]
    filled = torch.where(ok[..., None], stack, torch.nan)
    median = filled.nanmedian(dim=0).values
    return torch.where(torch.isnan(median), torch.full_like(median, 0.5), median)


ETERNAL_SHARE = 0.8
"""A carved point inside the hull of at least this share of the windows that see it is
there at every time; one inside fewer was seen around the times of those windows."""


def lifetimes(
    points: Float[Tensor, "P 3"], split: Split, shapes: Silhouettes
) -> tuple[Float[Tensor, "Q 3"], Float[Tensor, "Q 2"]]:
    """The points with their lifetimes (τ, σ). A point held by `ETERNAL_SHARE` of the
    windows that see it (what stays put), or by none, is there at every time: σ = inf.
    Otherwise it gets one lifetime per run of consecutive windows whose hulls hold it (a
    point that something passes twice is two Gaussians): τ the middle of the run's times,
    σ half their spread plus half the spacing of windows."""
    views = [i for i in range(len(split)) if shapes.masks[i] is not None]
    spans = windows(split, views)
    if len(spans) < 2:
        return points, torch.full((len(points), 2), math.inf)
    tests = [_hull_test(points.double(), split, span, shapes) for span in spans]
    held = torch.stack([h for h, _ in tests]).numpy()  # [W, P]
    looked = torch.stack([seen for _, seen in tests]).numpy()
    centres = np.array([float(split.times[span].double().mean()) for span in spans])
    count = held.sum(0)
    temporal = (count > 0) & (count < ETERNAL_SHARE * looked.sum(0))
    spacing = (centres[-1] - centres[0]) / (len(centres) - 1)
    rows, times = [np.flatnonzero(~temporal)], [np.full((int((~temporal).sum()), 2), np.inf)]
    start = np.full(len(points), -1)
    for w in range(len(spans) + 1):
        inside = held[w] & temporal if w < len(spans) else np.zeros(len(points), bool)
        ending = (start >= 0) & ~inside
        first, last = centres[start[ending]], centres[w - 1]
        rows.append(np.flatnonzero(ending))
        times.append(np.stack([(first + last) / 2, (last - first) / 2 + spacing / 2], 1))
        start = np.where(ending, -1, np.where(inside & (start < 0), w, start))
    order = torch.from_numpy(np.concatenate(rows))
    return points[order], torch.from_numpy(np.concatenate(times)).float()


# ---------------------------------------------------------------------------------------
# Triangulation

PAIRS = 24
"""Most view pairs matched for triangulation, spread over the sequence."""

BASELINE_DEGREES = (4.0, 60.0)
"""A pair's two views see the scene centre from directions this far apart: under the
lower bound depth is ill-posed, over the upper bound features no longer match."""

EPIPOLAR_PX = 1.5
"""Largest distance of a match from its epipolar line, and reprojection error, in pixels."""


def _projection(camera: Camera) -> np.ndarray:
    k = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1.0]])
    return k @ camera.world_to_camera.double().numpy()[:3]


def _pairs(split: Split, box: SceneBox) -> list[tuple[int, int]]:
    """View pairs of distinct viewpoints, as close in time as can be, whose directions to
    the scene centre are `BASELINE_DEGREES` apart; up to `PAIRS`, spread over time."""
    centre = torch.tensor(box.center, dtype=torch.float64)
    rays = torch.stack([(centre - c.center.double()) for c in split.cameras])
    rays = rays / rays.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    times = split.times.double()
    low, high = (math.cos(math.radians(d)) for d in BASELINE_DEGREES)
    order = sorted(range(len(split)), key=lambda i: float(times[i]))
    starts = np.linspace(0, len(order) - 1, min(PAIRS, len(order))).round().astype(int)
    pairs: list[tuple[int, int]] = []
    for start in sorted(set(starts.tolist())):
        i = order[start]
        cosine = rays @ rays[i]
        usable = (cosine <= low) & (cosine >= high)
        if not bool(usable.any()):
            continue
        gap = (times - times[i]).abs() + (cosine - 0.97).abs() * 1e-3  # then: ~14° apart
        j = int(torch.where(usable, gap, math.inf).argmin())
        pairs.append((i, j))
    return pairs


def _match(split: Split, i: int, j: int, sift: cv2.SIFT) -> tuple[np.ndarray, np.ndarray]:
    """SIFT matches between views i and j that pass Lowe's ratio test (0.75) and lie within
    `EPIPOLAR_PX` of the epipolar line the known poses give."""
    grey = [cv2.cvtColor(split.images[k].numpy(), cv2.COLOR_RGB2GRAY) for k in (i, j)]
    (kp1, d1), (kp2, d2) = (sift.detectAndCompute(g, None) for g in grey)
    if d1 is None or d2 is None or len(kp1) < 2 or len(kp2) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    good = [
        m
        for m, n in cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
        if m.distance < 0.75 * n.distance
    ]
    x1 = np.array([kp1[m.queryIdx].pt for m in good]).reshape(-1, 2)
    x2 = np.array([kp2[m.trainIdx].pt for m in good]).reshape(-1, 2)
    p1, p2 = _projection(split.cameras[i]), _projection(split.cameras[j])
    centre1 = split.cameras[i].center.double().numpy()
    epipole = p2 @ np.append(centre1, 1.0)
    skew = np.array(
        [[0, -epipole[2], epipole[1]], [epipole[2], 0, -epipole[0]], [-epipole[1], epipole[0], 0]]
    )
    fundamental = skew @ p2 @ np.linalg.pinv(p1)  # F = [e']ₓ P' P⁺ (Hartley and Zisserman)
    lines = np.c_[x1, np.ones(len(x1))] @ fundamental.T
    distance = np.abs((np.c_[x2, np.ones(len(x2))] * lines).sum(1)) / np.linalg.norm(
        lines[:, :2], axis=1
    ).clip(1e-12)
    keep = distance < EPIPOLAR_PX
    # OpenCV's keypoints have pixel centres at integers; ours at +0.5.
    return x1[keep] + 0.5, x2[keep] + 0.5


def triangulate(split: Split, box: SceneBox) -> Float[Tensor, "P 3"]:
    """Points triangulated from feature matches between view pairs (see the module
    docstring), kept where they lie in front of both views, reproject within
    `EPIPOLAR_PX`, and fall in the box grown by half."""
    sift = cv2.SIFT.create(nfeatures=4000)
    centre, half = np.array(box.center), 0.75 * (np.array(box.upper) - np.array(box.lower))
    found = []
    for i, j in _pairs(split, box):
        x1, x2 = _match(split, i, j, sift)
        if len(x1) == 0:
            continue
        p1, p2 = _projection(split.cameras[i]), _projection(split.cameras[j])
        homogeneous = cv2.triangulatePoints(
            p1, p2, x1.T.astype(np.float64), x2.T.astype(np.float64)
        )
        world = (homogeneous[:3] / homogeneous[3]).T
        ok = np.isfinite(world).all(1) & (np.abs(world - centre) <= half).all(1)
        for p, x in ((p1, x1), (p2, x2)):
            image = np.c_[world, np.ones(len(world))] @ p.T
            depth = image[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                error = np.linalg.norm(image[:, :2] / depth[:, None] - x, axis=1)
            ok &= (depth > 0) & (error < EPIPOLAR_PX)
        found.append(world[ok])
    points = np.concatenate(found) if found else np.zeros((0, 3))
    return torch.from_numpy(points).float()


# ---------------------------------------------------------------------------------------
# The choice

INITIAL_POINTS = ("auto", "file", "data", "random")
"""`--initial-points`: the module docstring's rules, the capture's own cloud whatever it
looks like, points made from the images even where a cloud came with them, or random."""

MIN_MADE = 100
"""Fewer points made from the images than this count as none."""


FLAT = 0.1
"""A cloud whose thinnest extent (1st–99th percentile) is under this share of its widest is
a surface (a floor, a wall), not a volume of noise; R, which compares against a volume,
does not apply to it."""


def is_flat(points: Float[Tensor, "P 3"]) -> bool:
    """Whether the cloud is much thinner along one axis than along another (`FLAT`)."""
    sample = points[:: max(1, len(points) // 20000)].double()
    extent = torch.quantile(sample, 0.99, dim=0) - torch.quantile(sample, 0.01, dim=0)
    return bool(extent.min() < FLAT * extent.max())


def judge_cloud(points: Tensor, split: Split, shapes: Silhouettes | None) -> str | None:
    """Why a given cloud looks like noise, or None when it looks real."""
    spread = 0.0 if is_flat(points) else aggregation_index(points)
    if spread >= NOISE_AGGREGATION:
        return f"spread like uniform noise (Clark–Evans R = {spread:.2f})"
    if shapes is not None and shapes.everything:
        agreement = silhouette_agreement(points, split, shapes)
        if agreement < NOISE_AGREEMENT:
            return f"mostly outside the silhouettes ({agreement:.0%} inside)"
    return None


def seeded_along_rays(
    split: Split, box: SceneBox, count: int, seed: int, fixed: FixedCameras | None
) -> tuple[Float[Tensor, "P 3"], Float[Tensor, "P 3"]]:
    """`count` points on the rays of random pixels of the split's viewpoints, each at a
    random depth inside the box and with its pixel's colour (on a fixed camera, the
    temporal median's, so that what moves does not stay behind). From its own camera
    such a point is right at any depth: the start for what a single viewpoint sees."""
    generator = torch.Generator().manual_seed(seed)
    if fixed is not None:
        sources = [
            (camera, median) for camera, median in zip(fixed.cameras, fixed.medians, strict=True)
        ]
    else:
        picks = np.linspace(0, len(split) - 1, min(64, len(split))).round().astype(int)
        sources = [(split.cameras[i], split.images[i]) for i in sorted(set(picks.tolist()))]
    points, colors = [], []
    for n, (camera, image) in enumerate(sources):
        share = count // len(sources) + (1 if n < count % len(sources) else 0)
        if share == 0:
            continue
        rows = torch.randint(camera.height, (share,), generator=generator)
        cols = torch.randint(camera.width, (share,), generator=generator)
        jitter = torch.rand(share, 2, generator=generator, dtype=torch.float64)
        pixels = torch.stack((cols, rows), -1).double() + jitter
        points.append(_rays_into_box(camera, pixels, box, generator))
        colors.append(image[rows, cols].float() / 255.0)
    return torch.cat(points).float(), torch.cat(colors)


_Part = tuple[Tensor, Tensor, Tensor, str]
"""Points, their colours, their lifetimes (τ, σ) and one phrase saying how they were made."""


def _carved(
    split: Split, shapes: Silhouettes, box: SceneBox, count: int, seed: int, how: str
) -> _Part:
    found, times = lifetimes(carve(split, shapes, box, count, seed), split, shapes)
    return found, colours(found, split, shapes), times, how


def _eternal(points: Tensor, colors: Tensor, how: str) -> _Part:
    return points, colors, torch.full((len(points), 2), math.inf), how


def _background(split: Split, box: SceneBox, count: int, seed: int) -> list[_Part]:
    """Where no silhouette shows all there is: triangulated points, topped up with points
    seeded along background rays."""
    found = triangulate(split, box)
    if len(found) > count:
        found = found[
            torch.randperm(len(found), generator=torch.Generator().manual_seed(seed))[:count]
        ]
    parts = [_eternal(found, colours(found, split, None), "triangulated from feature matches")]
    if len(found) < count:
        seeded = seeded_along_rays(split, box, count - len(found), seed, FixedCameras.of(split))
        parts.append(_eternal(*seeded, "on the rays of background pixels"))
    return parts


def made_from_data(
    scene: SceneData, box: SceneBox, count: int, pixel_change: float, seed: int
) -> Points | None:
    """Points made from the training images (see the module docstring), or None where
    nothing can be made. Half of them go to what moves where something is seen to. Carved
    points carry the times their windows saw them (`lifetimes`)."""
    train = scene.train
    shapes = silhouettes(train, scene.background)
    moving = shapes if shapes is not None and shapes.kind == "segmentation" else None
    if moving is None:
        moving = moving_silhouettes(train, pixel_change)
    share = count // 2 if moving is not None else count
    parts: list[_Part] = []
    if moving is not None:
        what = "foreground" if moving.kind == "segmentation" else "what moves in"
        how = f"carved from {what} {moving.count()} views"
        parts.append(_carved(train, moving, box, count - share, seed + 1, how))
    if shapes is not None and shapes.everything:
        how = f"carved from {shapes.count()} {shapes.kind} silhouettes"
        parts.append(_carved(train, shapes, box, share, seed, how))
    else:
        parts += _background(train, box, share, seed)
    parts = [part for part in parts if len(part[0]) > 0]
    if sum(len(part[0]) for part in parts) < MIN_MADE:
        return None
    said = ", ".join(f"{len(p):,} {how}" for p, _, _, how in parts)
    times = torch.cat([part[2] for part in parts])
    temporal = int(torch.isfinite(times[:, 1]).sum())
    if temporal:
        said += f"; {temporal:,} of them seen only around some times"
    return Points(torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts]), said, times)


def choose_initial_points(
    scene: SceneData, mode: str, count: int, pixel_change: float, seed: int
) -> tuple[SceneData, str]:
    """The scene with the initial points `mode` (`INITIAL_POINTS`) picks, and one line
    saying what they are."""
    given = not scene.points_source.startswith("random")
    if mode == "random" or (mode == "file" and given):
        return scene, f"{len(scene.points):,} initial points: {scene.points_source}"
    problem = None
    if given and mode == "auto":
        shapes = silhouettes(scene.train, scene.background)
        problem = judge_cloud(scene.points, scene.train, shapes)
        if problem is None:
            checked = dataclasses.replace(scene, points_on_surfaces=True)
            return checked, f"{len(scene.points):,} initial points from {scene.points_source}"
    # A cloud that is not used must not size the box either.
    box = scene_box_from_cameras(scene.train.cameras) if given else scene.scene_box
    made = made_from_data(scene, box, count, pixel_change, seed)
    if made is None:
        kept = f"kept ({problem})" if problem else scene.points_source
        return (
            scene,
            f"{len(scene.points):,} initial points, {kept}: none could be made from the images",
        )
    replaced = f"{scene.points_source} replaced, {problem}: " if problem else ""
    if given:
        box = scene_box_from_cameras(scene.train.cameras, made.points)
    chosen = dataclasses.replace(
        scene,
        points=made.points,
        point_colors=made.colors,
        point_lifetimes=made.lifetimes,
        scene_box=box,
        points_source=f"made from the images ({made.source})",
        points_on_surfaces=True,
    )
    return (
        chosen,
        f"{replaced}{len(made.points):,} initial points made from the images: {made.source}",
    )

"""The CPU reference renderer against the brute-force oracle, autograd's gradcheck and
hand-computed cases."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from dyngs.errors import ConfigError
from dyngs.renderers import cpu_reference, stages
from dyngs.renderers.base import Guards
from dyngs.renderers.cpu_reference import (
    CpuReferenceConfig,
    CpuReferenceRenderer,
    rasterize,
    zero_below,
)
from dyngs.renderers.cpu_tile import CpuTileConfig
from dyngs.renderers.stages import project
from dyngs.types import Camera, Gaussians
from tests.renderers.oracle import render_oracle
from tests.renderers.scenes import random_camera, random_gaussians, random_scene

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])

# Non-square images whose sides are not multiples of 16 (or of 8).
SIZES = [(61, 37), (45, 83), (100, 27)]
PLAIN = CpuReferenceConfig(antialiased=False)
"""The plain rule (3DGS's, no opacity compensation), which the oracle draws by default."""


def _max_abs(a: torch.Tensor, b: torch.Tensor, where: torch.Tensor | None = None) -> float:
    diff = (a.detach().double() - b.detach().double()).abs()
    if where is not None:
        diff = diff[where]
    return float(diff.max()) if diff.numel() else 0.0


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("tile_size", [16, 8, 4, None])
def test_float64_matches_oracle(seed: int, tile_size: int | None) -> None:
    width, height = SIZES[seed % len(SIZES)]
    sh_degree = [None, 0, 1, 2, 3, 3][seed]
    antialiased = seed % 2 == 1
    gaussians, camera, background = random_scene(seed, 300, width, height, torch.float64, sh_degree)
    renderer = CpuReferenceConfig(tile_size=tile_size, antialiased=antialiased).build()

    out = renderer(gaussians, camera, background, contribution=True)
    ref = render_oracle(gaussians, camera, background, antialiased=antialiased)

    assert out.rgb.shape == (height, width, 3) and out.rgb.dtype == torch.float64
    assert _max_abs(out.rgb, ref.rgb) <= 1e-9
    assert _max_abs(out.alpha, ref.alpha) <= 1e-9
    assert _max_abs(out.depth, ref.depth) <= 1e-9
    # The scene is not trivial: plenty of coverage, and some Gaussians are not drawn.
    assert float(ref.alpha.mean()) > 0.2
    assert 0 < int(out.visible.sum()) < len(gaussians)
    # Every Gaussian that reaches α ≥ 1/255 somewhere is inside the drawn set: the screen
    # extent never drops a pixel.
    assert bool((out.visible | ~ref.touches).all())
    # Each Gaussian's share of the picture (importance pruning reads it) is the oracle's,
    # counting only pixels inside the image although edge tiles overhang it.
    assert out.contribution is not None and out.contribution.dtype == torch.float64
    assert _max_abs(out.contribution, ref.contribution) <= 1e-9 * width * height
    assert float(ref.contribution.max()) > 1.0
    # Measuring it is optional and changes nothing else, bit for bit.
    plain = renderer(gaussians, camera, background)
    assert plain.contribution is None
    for got, want in [(plain.rgb, out.rgb), (plain.alpha, out.alpha), (plain.depth, out.depth)]:
        assert torch.equal(got, want)


@pytest.mark.parametrize("seed", range(6))
def test_float32_matches_oracle(seed: int) -> None:
    width, height = SIZES[seed % len(SIZES)]
    sh_degree = [None, 0, 1, 2, 3, None][seed]
    antialiased = seed % 2 == 0
    gaussians, camera, background = random_scene(
        100 + seed, 400, width, height, torch.float32, sh_degree
    )
    renderer = CpuReferenceConfig(antialiased=antialiased).build()

    out = renderer(gaussians, camera, background, contribution=True)
    ref = render_oracle(gaussians, camera, background, antialiased=antialiased)

    assert out.rgb.dtype == torch.float32
    # Where a threshold decision (α vs 1/255, T vs 1e-4) lies within float32 rounding of
    # its threshold, either answer is right; such pixels are rare and are left out.
    robust = ~ref.fragile
    assert float(robust.float().mean()) > 0.99
    for got, want in ((out.rgb, ref.rgb), (out.alpha, ref.alpha), (out.depth, ref.depth)):
        assert _max_abs(got, want, robust) <= 1e-5
    assert float(ref.alpha.mean()) > 0.2


@pytest.mark.parametrize("spread", [1.5, 6.0])
def test_scenes_around_and_behind_the_camera(spread: float) -> None:
    """A wide spread puts Gaussians behind the camera, at the near plane and far off screen."""
    gen = torch.Generator().manual_seed(7)
    camera = random_camera(gen, 53, 41)
    gaussians = random_gaussians(gen, 500, spread=spread)
    background = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)
    out = CpuReferenceRenderer(PLAIN)(gaussians, camera, background)
    ref = render_oracle(gaussians, camera, background)
    for got, want in ((out.rgb, ref.rgb), (out.alpha, ref.alpha), (out.depth, ref.depth)):
        assert _max_abs(got, want) <= 1e-9


def test_output_shapes_and_screen_data() -> None:
    gaussians, camera, background = random_scene(3, 200, 45, 29, torch.float32)
    out = CpuReferenceRenderer(PLAIN)(gaussians, camera, background)
    n = len(gaussians)
    assert out.alpha.shape == (29, 45, 1) and out.depth.shape == (29, 45, 1)
    assert out.means2d.shape == (n, 2) and out.radii.shape == (n, 2) and out.visible.shape == (n,)
    assert bool((out.radii[~out.visible] == 0).all())
    assert bool((out.radii[out.visible] > 0).all())


# ---------------------------------------------------------------------------------------
# Gradients


def _tiny_scene(sh_degree: int | None, seed: int = 0) -> tuple[Gaussians, Camera, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    camera = Camera(22.0, 20.0, 9.3, 6.1, torch.eye(4, dtype=torch.float64), 19, 13)
    n = 5
    means = torch.rand(n, 3, generator=gen, dtype=torch.float64) * torch.tensor([1.2, 0.8, 1.0])
    means = means + torch.tensor([-0.6, -0.4, 2.0])
    quats = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    scales = 0.05 + 0.1 * torch.rand(n, 3, generator=gen, dtype=torch.float64)
    opacities = 0.3 + 0.5 * torch.rand(n, generator=gen, dtype=torch.float64)
    if sh_degree is None:
        colors = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    else:
        colors = 0.3 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=gen, dtype=torch.float64)
    background = torch.tensor([0.1, 0.5, 0.9], dtype=torch.float64)
    return Gaussians(means, quats, scales, opacities, colors, sh_degree), camera, background


@pytest.mark.slow
@pytest.mark.parametrize("sh_degree", [None, 3])
@pytest.mark.parametrize("antialiased", [False, True])
def test_gradcheck_gaussian_parameters(sh_degree: int | None, antialiased: bool) -> None:
    base, camera, background = _tiny_scene(sh_degree)
    renderer = CpuReferenceConfig(antialiased=antialiased, tile_size=8).build()
    weights = torch.rand(camera.height, camera.width, 5, generator=torch.Generator().manual_seed(1),
                         dtype=torch.float64)  # fmt: skip

    def image(means, quats, scales, opacities, colors):  # type: ignore[no-untyped-def]
        g = Gaussians(means, quats, scales, opacities, colors, sh_degree)
        out = renderer(g, camera, background)
        return (torch.cat((out.rgb, out.alpha, out.depth), -1) * weights).sum(-1)

    inputs = tuple(
        t.clone().requires_grad_(True)
        for t in (base.means, base.quats, base.scales, base.opacities, base.colors)
    )
    assert torch.autograd.gradcheck(image, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.slow
def test_gradcheck_screen_space_means() -> None:
    """The image as a function of the 2D means alone, the quantity densification reads."""
    gaussians, camera, background = _tiny_scene(None, seed=2)
    screen = project(gaussians, camera, Guards())
    assert int(screen.visible.sum()) == len(gaussians)

    def image(means2d: torch.Tensor) -> torch.Tensor:
        moved = replace(screen, means2d=means2d)
        rgb, alpha, depth = rasterize(moved, camera.width, camera.height, background, tile_size=8)
        return torch.cat((rgb, alpha, depth), -1)

    means2d = screen.means2d.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(image, (means2d,), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_means2d_receive_gradients() -> None:
    gaussians, camera, background = random_scene(5, 200, 40, 30, torch.float32)
    gaussians.means.requires_grad_(True)
    out = CpuReferenceRenderer(PLAIN)(gaussians, camera, background)
    out.rgb.sum().backward()
    grad = out.means2d.grad
    assert grad is not None and grad.shape == (len(gaussians), 2)
    assert bool((grad[~out.visible] == 0).all())
    assert float(grad[out.visible].abs().sum(-1).gt(0).float().mean()) > 0.5


# ---------------------------------------------------------------------------------------
# Hand-computed cases


def _single(z: float, scale: float, opacity: float, color: list[float], dtype=torch.float64):  # type: ignore[no-untyped-def]
    return Gaussians(
        torch.tensor([[0.0, 0.0, z]], dtype=dtype),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype),
        torch.full((1, 3), scale, dtype=dtype),
        torch.tensor([opacity], dtype=dtype),
        torch.tensor([color], dtype=dtype),
    )


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_one_gaussian_centred_on_a_pixel(dtype: torch.dtype) -> None:
    # Centre on pixel (row 4, column 6): the principal point sits at that pixel's centre.
    camera = Camera(50.0, 50.0, 6.5, 4.5, torch.eye(4, dtype=dtype), 13, 9)
    g = _single(z=2.0, scale=0.04, opacity=0.7, color=[1.0, 0.5, 0.25], dtype=dtype)
    background = torch.tensor([0.0, 0.0, 1.0], dtype=dtype)
    out = CpuReferenceRenderer(PLAIN)(g, camera, background)

    tol = 1e-12 if dtype == torch.float64 else 1e-6
    assert abs(float(out.alpha[4, 6, 0]) - 0.7) < tol
    expected = [0.7 * 1.0, 0.7 * 0.5, 0.7 * 0.25 + 0.3 * 1.0]
    assert torch.allclose(
        out.rgb[4, 6].double(), torch.tensor(expected, dtype=torch.float64), atol=tol
    )
    assert abs(float(out.depth[4, 6, 0]) - 2.0) < 1e-5
    # One pixel to the right: σ² = (f·s/z)² + 0.3 = 1 + 0.3.
    assert abs(float(out.alpha[4, 7, 0]) - 0.7 * math.exp(-0.5 / 1.3)) < tol
    assert abs(float(out.alpha[5, 7, 0]) - 0.7 * math.exp(-1.0 / 1.3)) < tol
    assert out.means2d[0].tolist() == pytest.approx([6.5, 4.5])


def test_two_overlapping_gaussians_composite_in_depth_order() -> None:
    camera = Camera(50.0, 50.0, 2.5, 2.5, torch.eye(4, dtype=torch.float64), 5, 5)
    near = _single(z=2.0, scale=0.05, opacity=0.6, color=[1.0, 0.0, 0.0])
    far = _single(z=3.0, scale=0.05, opacity=0.5, color=[0.0, 1.0, 0.0])
    background = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    expected_rgb = torch.tensor([0.6, 0.4 * 0.5, 0.4 * 0.5], dtype=torch.float64)
    expected_alpha = 0.6 + 0.4 * 0.5
    expected_depth = (0.6 * 2.0 + 0.4 * 0.5 * 3.0) / expected_alpha
    for first, second in ((near, far), (far, near)):  # input order must not matter
        means, quats, scales, opacities, colors = (
            torch.cat((getattr(first, k), getattr(second, k)))
            for k in ("means", "quats", "scales", "opacities", "colors")
        )
        g = Gaussians(means, quats, scales, opacities, colors)
        out = CpuReferenceRenderer(PLAIN)(g, camera, background)
        assert torch.allclose(out.rgb[2, 2], expected_rgb, atol=1e-12)
        assert abs(float(out.alpha[2, 2, 0]) - expected_alpha) < 1e-12
        assert abs(float(out.depth[2, 2, 0]) - expected_depth) < 1e-12


def test_gaussian_behind_the_camera_draws_nothing_and_gets_no_gradient() -> None:
    camera = Camera(50.0, 50.0, 8.0, 8.0, torch.eye(4, dtype=torch.float64), 16, 16)
    g = _single(z=-2.0, scale=0.5, opacity=0.9, color=[1.0, 0.0, 0.0])
    for name in ("means", "quats", "scales", "opacities", "colors"):
        getattr(g, name).requires_grad_(True)
    background = torch.tensor([0.3, 0.3, 0.3], dtype=torch.float64)
    out = CpuReferenceRenderer(PLAIN)(g, camera, background)
    assert bool((out.rgb == background).all())
    assert bool((out.alpha == 0).all()) and bool((out.depth == 0).all())
    assert not bool(out.visible[0]) and out.radii[0].tolist() == [0, 0]
    (out.rgb.sum() + out.alpha.sum() + out.depth.sum()).backward()
    for name in ("means", "quats", "scales", "opacities", "colors"):
        grad = getattr(g, name).grad
        assert grad is None or bool((grad == 0).all()), name


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_devices_and_dtypes(device: str, dtype: torch.dtype) -> None:
    gaussians, camera, background = random_scene(11, 150, 33, 21, dtype, sh_degree=2)
    moved = gaussians.to(device)
    out = CpuReferenceRenderer(PLAIN)(moved, camera.to(device), background.to(device))
    assert out.rgb.device.type == device and out.rgb.dtype == dtype
    ref = render_oracle(gaussians, camera, background)
    tol = 1e-9 if dtype == torch.float64 else 1e-5
    assert _max_abs(out.rgb.cpu(), ref.rgb, ~ref.fragile) <= tol


def _crowded_corner_scene() -> tuple[Gaussians, Camera, torch.Tensor]:
    """A few hundred Gaussians piled into one corner plus a sparse scatter: tile depth
    complexities from a handful to hundreds, the shape that made padding expensive."""
    gen = torch.Generator().manual_seed(11)
    camera = random_camera(gen, 48, 40, torch.float64)
    sparse = random_gaussians(gen, 60, torch.float64, sh_degree=1)
    sparse = replace(sparse, scales=sparse.scales * 0.1)
    pile = random_gaussians(gen, 300, torch.float64, sh_degree=1, spread=0.15)
    corner = torch.linalg.solve(camera.world_to_camera[:3, :3], torch.tensor([-0.5, -0.4, 4.0],
                                dtype=torch.float64) - camera.world_to_camera[:3, 3])  # fmt: skip
    pile = replace(pile, means=pile.means + corner, scales=pile.scales * 0.3)
    merged = Gaussians(
        torch.cat((sparse.means, pile.means)),
        torch.cat((sparse.quats, pile.quats)),
        torch.cat((sparse.scales, pile.scales)),
        torch.cat((sparse.opacities, pile.opacities)),
        torch.cat((sparse.colors, pile.colors)),
        1,
    )
    return merged, camera, torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)


@pytest.mark.parametrize("fill", [0.0, 0.75, 1.0])
@pytest.mark.parametrize("chunk_elements", [1, 1 << 12, 1 << 24])
def test_chunking_changes_neither_image_nor_gradients(
    fill: float, chunk_elements: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """How tiles are grouped and padded is a speed choice only: one tile per chunk, the
    default grouping and one chunk for everything give the same image and gradients."""
    gaussians, camera, background = _crowded_corner_scene()

    def render(fill: float, chunk_elements: int) -> tuple[torch.Tensor, ...]:
        monkeypatch.setattr(cpu_reference, "_CHUNK_FILL", fill)
        inputs = [t.clone().requires_grad_(True) for t in (gaussians.means, gaussians.colors)]
        g = replace(gaussians, means=inputs[0], colors=inputs[1])
        renderer = CpuReferenceConfig(chunk_elements=chunk_elements).build()
        out = renderer(g, camera, background, contribution=True)
        (out.rgb.sum() + out.depth.sum()).backward()
        assert out.contribution is not None
        return out.rgb, out.depth, out.contribution, inputs[0].grad, inputs[1].grad  # type: ignore[return-value]

    counts = _tile_counts(gaussians, camera)
    assert max(counts) > 10 * sorted(counts)[len(counts) // 2]  # the scene is lopsided
    reference = render(0.0, 1 << 30)  # everything in one chunk, padded to the busiest tile
    for got, want in zip(render(fill, chunk_elements), reference, strict=True):
        assert _max_abs(got, want) <= 1e-12


def _tile_counts(gaussians: Gaussians, camera: Camera) -> list[int]:
    screen = project(gaussians, camera, Guards())
    return stages.bin_tiles(screen, camera.width, camera.height, 8).tile_count.tolist()


@pytest.mark.parametrize("seed", range(20))
def test_chunks_cover_every_busy_tile_once_within_budget(seed: int) -> None:
    gen = torch.Generator().manual_seed(seed)
    counts = sorted((torch.rand(int(torch.randint(1, 300, (1,), generator=gen)), generator=gen)
                     ** 6 * 2000).long().tolist(), reverse=True)  # fmt: skip
    budget = int(torch.randint(1, 5000, (1,), generator=gen))
    ranges = cpu_reference._chunks(counts, budget)
    busy = sum(1 for n in counts if n > 0)
    assert [i for start, stop in ranges for i in range(start, stop)] == list(range(busy))
    for start, stop in ranges:
        assert stop - start == 1 or (stop - start) * counts[start] <= budget
        # No tile is padded to more than 1/_CHUNK_FILL times its own count.
        assert counts[stop - 1] >= cpu_reference._CHUNK_FILL * counts[start]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_antialiasing_a_degenerate_covariance_keeps_every_gradient_finite(
    dtype: torch.dtype,
) -> None:
    """A Gaussian with zero scales has a 2D covariance of 0 before the dilation, so its
    compensation √(det Σ / det(Σ + 0.3 I)) is √0, whose derivative is infinite: it must
    get no gradient (and so no NaN) rather than 0 · ∞, as in the compiled projection."""
    gaussians, camera, background = random_scene(3, 40, 31, 23, dtype)
    scales = gaussians.scales.clone()
    scales[:5] = 0.0  # degenerate: drawn as the dilation alone, compensated to nothing
    gaussians = replace(gaussians, scales=scales)
    for config in (CpuReferenceConfig(antialiased=True), CpuTileConfig(antialiased=True)):
        renderer = config.build()
        leaves = {
            name: getattr(gaussians, name).detach().clone().requires_grad_(True)
            for name in ("means", "quats", "scales", "opacities", "colors")
        }
        out = renderer(replace(gaussians, **leaves), camera, background)
        (out.rgb * torch.linspace(0.1, 1.0, 3, dtype=dtype)).sum().backward()
        assert float(out.alpha.detach().amax()) > 0.1  # the other Gaussians are drawn
        for name, leaf in leaves.items():
            assert leaf.grad is not None and bool(leaf.grad.isfinite().all()), name
            if name in ("means", "quats", "scales"):
                assert float(leaf.grad[:5].abs().max()) == 0.0, name


def test_far_below_threshold_pairs_are_dropped_exactly() -> None:
    """Pairs whose log-α is far below ln(α_min) (padding, distant pixels) have their
    exponent raised before exp for speed; a Gaussian just above α_min at a pixel still
    draws, and one just below draws nothing."""
    # The Gaussian projects onto the centre of pixel (4, 4), where its α is its opacity.
    camera = Camera(20.0, 20.0, 4.5, 4.5, torch.eye(4, dtype=torch.float64), 8, 8)
    background = torch.zeros(3, dtype=torch.float64)

    def peak_alpha(opacity: float) -> float:
        g = Gaussians(
            torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64),
            torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64),
            torch.full((1, 3), 0.01, dtype=torch.float64),
            torch.tensor([opacity], dtype=torch.float64),
            torch.ones(1, 3, dtype=torch.float64),
            None,
        )
        return float(CpuReferenceRenderer(PLAIN)(g, camera, background).alpha.max())

    threshold = Guards().alpha_min
    assert peak_alpha(0.5) == pytest.approx(0.5, rel=1e-12)
    assert peak_alpha(threshold * 1.001) == pytest.approx(threshold * 1.001, rel=1e-12)
    assert peak_alpha(threshold * 0.999) == 0.0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("floor", [1 / 255, 1e-4, 0.5])
def test_zero_below_is_the_boolean_mask_exactly(dtype: torch.dtype, floor: float) -> None:
    """`zero_below` (the fast path compositing uses) against the obvious definition,
    `x.masked_fill(x < floor, 0)`, bit for bit in value and gradient, including the
    numbers of the dtype on either side of the floor and the floor itself."""
    at = torch.tensor(floor, dtype=dtype)
    edges = [at]
    for direction in (-math.inf, math.inf):
        step = at
        for _ in range(3):
            step = torch.nextafter(step, torch.tensor(direction, dtype=dtype))
            edges.append(step)
    x = torch.cat(
        (
            torch.stack(edges),
            torch.rand(200, dtype=dtype, generator=torch.Generator().manual_seed(0)),
            torch.tensor([0.0, 1.0], dtype=dtype),
        )
    )
    fast_input = x.clone().requires_grad_()
    slow_input = x.clone().requires_grad_()
    fast = zero_below(fast_input, floor)
    slow = slow_input.masked_fill(slow_input < floor, 0)
    assert torch.equal(fast, slow)
    assert (fast[: len(edges)] > 0).tolist() == [bool(e >= at) for e in edges]
    weights = torch.linspace(1, 2, len(x), dtype=dtype)
    (fast * weights).sum().backward()
    (slow * weights).sum().backward()
    assert fast_input.grad is not None and slow_input.grad is not None
    assert torch.equal(fast_input.grad, slow_input.grad)


@pytest.mark.parametrize("seed", range(4))
def test_tile_pair_counts_are_what_binning_makes(seed: int) -> None:
    width, height = SIZES[seed % len(SIZES)]
    gaussians, camera, _ = random_scene(seed, 300, width, height, torch.float64)
    screen = project(gaussians, camera, Guards())
    sizes = (4, 5, 8, 16)
    binned = [int(stages.bin_tiles(screen, width, height, s).tile_count.sum()) for s in sizes]
    assert cpu_reference.tile_pair_counts(screen, width, height, sizes) == binned
    assert binned[0] > binned[-1] > 0


@pytest.mark.parametrize(("scale", "expected"), [(0.01, 4), (1.0, 16)])
def test_small_gaussians_get_small_tiles_and_large_ones_large_tiles(
    scale: float, expected: int
) -> None:
    """σ of 0.5 px wastes most of an 8×8 tile's pixels; σ of 50 px covers the whole
    128² image, where 16×16 tiles make a quarter of the pairs that 8×8 tiles do."""
    gen = torch.Generator().manual_seed(0)
    n = 200
    means = torch.cat((torch.rand(n, 2, generator=gen, dtype=torch.float64) * 2 - 1,
                       torch.full((n, 1), 2.0, dtype=torch.float64)), dim=1)  # fmt: skip
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64).expand(n, 4)
    gaussians = Gaussians(means, quats, torch.full((n, 3), scale, dtype=torch.float64),
                          torch.full((n,), 0.5, dtype=torch.float64),
                          torch.rand(n, 3, generator=gen, dtype=torch.float64), None)  # fmt: skip
    camera = Camera(100.0, 100.0, 64.0, 64.0, torch.eye(4, dtype=torch.float64), 128, 128)
    screen = project(gaussians, camera, Guards())
    assert cpu_reference.choose_tile_size(screen, 128, 128) == expected
    # The choice is the least expected work over the binnings it chooses from.
    work = {
        size: int(stages.bin_tiles(screen, 128, 128, size).tile_count.sum())
        * (cpu_reference._PAIR_COST + size * size)
        for size in cpu_reference._TILE_SIZES
    }
    assert min(work, key=work.__getitem__) == expected
    background = torch.zeros(3, dtype=torch.float64)
    auto = CpuReferenceRenderer()(gaussians, camera, background)
    fixed = CpuReferenceConfig(tile_size=8).build()(gaussians, camera, background)
    assert _max_abs(auto.rgb, fixed.rgb) <= 1e-12


def test_tile_size_must_be_positive() -> None:
    with pytest.raises(ConfigError, match="tile-size must be ≥ 1"):
        CpuReferenceConfig(tile_size=0)


@pytest.mark.parametrize("cx", [32.0, 20.0, 50.5])
def test_off_axis_clamp_follows_the_image_edges(cx: float) -> None:
    # The EWA Jacobian's clamp reaches 0.3·tan(fov/2) past each edge of the image, wherever
    # the principal point is (gsplat's bounds); for a centred one that is Kerbl et al.'s
    # ±1.3·tan(fov/2) about the axis.
    width, height, fx, fy = 64, 48, 80.0, 70.0
    camera = Camera(fx, fy, cx, 24.0, torch.eye(4, dtype=torch.float64), width, height)
    left, right, top, bottom = stages.off_axis_limits(camera, Guards())
    margin_px = 0.3 * width / 2  # the margin in pixels: tan(fov/2)·fx = width / 2
    assert cx - fx * left == pytest.approx(-margin_px)
    assert cx + fx * right == pytest.approx(width + margin_px)
    assert top == pytest.approx(bottom) == pytest.approx(1.3 * 0.5 * height / fy)
    if cx == width / 2:
        assert left == pytest.approx(right) == pytest.approx(1.3 * 0.5 * width / fx)

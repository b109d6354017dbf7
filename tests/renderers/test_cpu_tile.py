"""`cpu-tile` held to `cpu-reference`, the specification: images, contributions and every
gradient on random scenes, gradcheck of the compiled backward, and the properties that
make it usable for training (deterministic, independent of threads and tile size). The
hard cases run on it too (test_hard_cases.py)."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
import torch
from torch import Tensor

from dyngs.errors import ConfigError, RendererUnavailable
from dyngs.renderers import cpu_tile
from dyngs.renderers.base import Guards, RenderOutput
from dyngs.renderers.cpu_reference import CpuReferenceConfig
from dyngs.renderers.cpu_tile import CpuTileConfig
from dyngs.renderers.stages import ScreenGaussians, TileBins, bin_tiles, project
from dyngs.types import Camera, Gaussians
from tests.renderers.scenes import random_scene
from tests.renderers.test_cpu_reference import _tiny_scene

PARAMS = ("means", "quats", "scales", "opacities", "colors")


def _render(
    config: CpuReferenceConfig | CpuTileConfig,
    gaussians: Gaussians,
    camera: Camera,
    background: Tensor,
) -> tuple[RenderOutput, dict[str, Tensor]]:
    """A render with contribution measured, and the gradients of a loss that weighs every
    output channel differently (so no gradient cancels by symmetry)."""
    leaves = {
        name: getattr(gaussians, name).detach().clone().requires_grad_(True) for name in PARAMS
    }
    out = config.build()(Gaussians(**leaves, sh_degree=gaussians.sh_degree), camera, background,
                         contribution=True)  # fmt: skip
    gen = torch.Generator().manual_seed(7)
    weights = torch.randn(*out.rgb.shape[:2], 5, generator=gen, dtype=torch.float64)
    stacked = torch.cat((out.rgb, out.alpha, out.depth), -1)
    (stacked * weights.to(stacked.dtype)).sum().backward()
    grads = {name: leaf.grad for name, leaf in leaves.items()}
    grads["means2d"] = out.means2d.grad
    # Not a gradient, but filled by the same backward, and held to the same tolerance.
    grads["means2d_absgrad"] = out.means2d_absgrad
    return out, {name: grad for name, grad in grads.items() if grad is not None}


def _assert_parity(got: RenderOutput, want: RenderOutput, dtype: torch.dtype) -> None:
    tolerance = 1e-9 if dtype == torch.float64 else 1e-5
    for name in ("rgb", "alpha", "depth"):
        diff = float((getattr(got, name) - getattr(want, name)).detach().abs().max())
        assert diff <= tolerance, f"{name} differs by {diff:.3g}"
    assert torch.equal(got.visible, want.visible) and torch.equal(got.radii, want.radii)
    assert got.contribution is not None and want.contribution is not None
    scale = float(want.contribution.abs().max())
    assert float((got.contribution - want.contribution).abs().max()) <= tolerance * max(scale, 1)


def _assert_gradients_match(got: dict[str, Tensor], want: dict[str, Tensor], dtype: torch.dtype):  # type: ignore[no-untyped-def]
    relative = 1e-9 if dtype == torch.float64 else 1e-4
    assert got.keys() == want.keys()
    for name, grad in want.items():
        scale = float(grad.abs().max())
        assert scale > 0, f"no gradient reached {name}"
        diff = float((got[name] - grad).abs().max())
        assert diff <= relative * scale, f"∂/∂{name}: {diff:.3g} of {scale:.3g}"


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize(
    ("seed", "n", "width", "height", "sh_degree"),
    [
        (0, 300, 97, 61, None),
        (1, 800, 64, 48, 0),
        (2, 2000, 33, 129, 1),
        (3, 1200, 130, 70, 2),
        (4, 3000, 101, 101, 3),
        (5, 3000, 160, 131, 1),  # tiles of 32 px (`choose_tile_size`)
    ],
)
def test_images_contributions_and_gradients_match_the_reference(
    dtype: torch.dtype, seed: int, n: int, width: int, height: int, sh_degree: int | None
) -> None:
    gaussians, camera, background = random_scene(seed, n, width, height, dtype, sh_degree)
    want, want_grads = _render(CpuReferenceConfig(), gaussians, camera, background)
    got, got_grads = _render(CpuTileConfig(), gaussians, camera, background)
    assert bool(want.visible.sum() > n // 4), "the scene should draw many Gaussians"
    _assert_parity(got, want, dtype)
    _assert_gradients_match(got_grads, want_grads, dtype)


@pytest.mark.parametrize("antialiased", [False, True])
def test_antialiased_matches_the_reference(antialiased: bool) -> None:
    gaussians, camera, background = random_scene(11, 500, 80, 60, torch.float64, 2)
    want, want_grads = _render(CpuReferenceConfig(antialiased=antialiased), gaussians, camera,
                               background)  # fmt: skip
    got, got_grads = _render(CpuTileConfig(antialiased=antialiased), gaussians, camera, background)
    _assert_parity(got, want, torch.float64)
    _assert_gradients_match(got_grads, want_grads, torch.float64)


@pytest.mark.slow
@pytest.mark.parametrize("sh_degree", [None, 3])
def test_gradcheck_gaussian_parameters(sh_degree: int | None) -> None:
    base, camera, background = _tiny_scene(sh_degree)
    renderer = CpuTileConfig(tile_size=8).build()
    gen = torch.Generator().manual_seed(1)
    weights = torch.rand(camera.height, camera.width, 5, generator=gen, dtype=torch.float64)

    def image(means, quats, scales, opacities, colors):  # type: ignore[no-untyped-def]
        out = renderer(Gaussians(means, quats, scales, opacities, colors, sh_degree), camera,
                       background)  # fmt: skip
        return (torch.cat((out.rgb, out.alpha, out.depth), -1) * weights).sum(-1)

    inputs = tuple(getattr(base, name).clone().requires_grad_(True) for name in PARAMS)
    assert torch.autograd.gradcheck(image, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def _plan_of_counts(counts: list[int], threads: int) -> cpu_tile._Plan:
    """A plan whose tiles hold `counts` Gaussians (the pairs themselves do not matter)."""
    count = torch.tensor(counts)
    bins = TileBins(torch.zeros(int(count.sum()), dtype=torch.long), count.cumsum(0) - count,
                    count)  # fmt: skip
    return cpu_tile._Plan(bins, (8 * len(counts), 8, 8), Guards(), threads, False, True)


def test_tiles_are_dealt_busiest_first_to_the_least_loaded_thread() -> None:
    order, bounds = _plan_of_counts([0, 5, 3, 3, 2, 0, 7, 1], 2).deal()
    # 7 → thread 0; 5, 3 → thread 1 (5, then 8 < 7 + 3); 3 → thread 0 (10); 2 → thread 1
    # (10); 1 → thread 0, the first of two equally loaded.
    assert bounds.tolist() == [0, 3, 6]
    assert order.tolist() == [6, 3, 7, 1, 2, 4]
    order, bounds = _plan_of_counts([0, 5, 3, 3, 2, 0, 7, 1], 1).deal()
    assert bounds.tolist() == [0, 6] and order.tolist() == [6, 1, 2, 3, 4, 7]


@pytest.mark.parametrize("threads", [1, 2, 7])
def test_every_busy_tile_is_dealt_once_and_no_thread_is_loaded_past_lpts_bound(
    threads: int,
) -> None:
    gen = torch.Generator().manual_seed(threads)
    counts = torch.randint(0, 40, (57,), generator=gen) * (torch.rand(57, generator=gen) > 0.3)
    order, bounds = _plan_of_counts(counts.tolist(), threads).deal()
    threads = len(bounds) - 1  # within numba's pool (thread_count)
    assert sorted(order.tolist()) == counts.nonzero().squeeze(1).tolist()
    assert bounds[0] == 0 and bounds[-1] == len(order) and (np.diff(bounds) >= 0).all()
    loads = [int(counts[order[bounds[j] : bounds[j + 1]]].sum()) for j in range(threads)]
    # Graham: the last tile placed went to the least loaded thread, so no thread ends
    # more than one tile's work above the mean.
    assert max(loads) <= sum(loads) / threads + int(counts.max())


def test_gradcheck_of_the_compiled_compositing() -> None:
    """The kernels alone, as a function of every input they differentiate: 2D means,
    conics, ln opacity and the blended features."""
    gaussians, camera, _ = _tiny_scene(None, seed=2)
    screen = project(gaussians, camera, Guards())
    size = (camera.width, camera.height, 8)
    bins = bin_tiles(screen, *size)
    plan = cpu_tile._Plan(bins, size, Guards(), None, False, True)
    features = torch.cat((screen.colors, screen.depths[:, None]), 1)

    def sums(means2d: Tensor, conics: Tensor, log_opacity: Tensor, feats: Tensor) -> Tensor:
        return cpu_tile._Composite.apply(means2d, conics, log_opacity, feats, plan)[0]

    inputs = tuple(
        t.detach().clone().requires_grad_(True)
        for t in (screen.means2d, screen.conics, screen.opacities.log(), features)
    )
    assert torch.autograd.gradcheck(sums, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_a_render_without_gradients_keeps_no_backward_state_and_draws_the_same(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    gaussians, camera, background = random_scene(6, 1500, 77, 53, torch.float32, 2)
    renderer = CpuTileConfig().build()
    kept: list[tuple[int, int, int, int]] = []
    launch = cpu_tile._launch

    def spy(kernel: Any, threads: int | None, *args: Any) -> None:
        if kernel.__name__ == "composite_forward":
            transmittance, _, alphas, feet = args[5]  # what the forward keeps for backward
            kept.append((*transmittance.shape, len(feet), alphas.shape[1]))
        launch(kernel, threads, *args)

    monkeypatch.setattr(cpu_tile, "_launch", spy)
    leaves = {name: getattr(gaussians, name).clone().requires_grad_(True) for name in PARAMS}
    with_grad = renderer(Gaussians(**leaves, sh_degree=2), camera, background, contribution=True)
    with torch.no_grad():
        without = renderer(Gaussians(**leaves, sh_degree=2), camera, background, contribution=True)
    still = renderer(gaussians, camera, background, contribution=True)  # nothing requires grad
    # Without backward: no per-pixel state, no footprints, and one tile's α a thread.
    from dyngs.renderers import tile_kernels

    tile = tile_kernels.tile_cells(cpu_tile.choose_tile_size(camera.width, camera.height))
    assert kept[0][:2] == (camera.height, camera.width) and kept[0][2] > 0
    assert kept[1:] == [(0, 0, 0, tile), (0, 0, 0, tile)]
    for out in (without, still):
        for name in ("rgb", "alpha", "depth", "contribution"):
            assert torch.equal(getattr(out, name), getattr(with_grad, name).detach()), name


def test_the_alphas_kept_for_backward_are_reused_only_once_their_graph_is_freed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The forward keeps each pair's α for the backward in an array that later renders
    # reuse (`cpu_tile._AlphaStore`). A graph still alive keeps its own: backward through it,
    # twice, while other renders come and go, gives the gradients of a render on its own.
    renderer = CpuTileConfig(threads=2).build()
    arrays: list[np.ndarray] = []
    launch = cpu_tile._launch

    def spy(kernel: Any, threads: int | None, *args: Any) -> None:
        if kernel.__name__ == "composite_forward":
            arrays.append(args[5][2])
        launch(kernel, threads, *args)

    monkeypatch.setattr(cpu_tile, "_launch", spy)

    def loss(seed: int) -> tuple[Tensor, dict[str, Tensor]]:
        gaussians, camera, background = random_scene(seed, 1500, 77, 53, torch.float32, 2)
        leaves = {name: getattr(gaussians, name).clone().requires_grad_(True) for name in PARAMS}
        out = renderer(Gaussians(**leaves, sh_degree=2), camera, background)
        weights = torch.linspace(-1.0, 1.0, out.rgb.numel()).view_as(out.rgb)
        return (out.rgb * weights).sum() + out.alpha.sum(), leaves

    first, leaves = loss(6)
    first.backward()
    want = {name: leaf.grad.clone() for name, leaf in leaves.items() if leaf.grad is not None}
    del first, leaves
    kept, leaves = loss(6)
    for seed in (7, 8, 9):
        other, _ = loss(seed)
        other.backward()
        del other
    # `kept` took the first render's array once that graph was freed; the others, each
    # freed before the next, all reused one more array, never the one `kept`'s graph holds.
    assert arrays[1] is arrays[0]
    assert arrays[2] is arrays[3] is arrays[4] and arrays[2] is not arrays[1]
    for _ in range(2):
        for leaf in leaves.values():
            leaf.grad = None
        kept.backward(retain_graph=True)
        for name, grad in want.items():
            got = leaves[name].grad
            assert got is not None and torch.equal(got, grad), name


def test_the_same_render_on_every_run_and_thread_count() -> None:
    gaussians, camera, background = random_scene(5, 2000, 90, 70, torch.float32, 3)
    runs = [
        _render(CpuTileConfig(threads=threads), gaussians, camera, background)
        for threads in (1, 2, 2)
    ]
    (first, first_grads), *others = runs
    for out, grads in others:
        assert torch.equal(out.rgb, first.rgb) and torch.equal(out.depth, first.depth)
        assert out.contribution is not None and first.contribution is not None
        assert torch.equal(out.contribution, first.contribution)
        for name, grad in grads.items():
            assert torch.equal(grad, first_grads[name]), name


@pytest.mark.parametrize("tile_size", [1, 7, 16, 32])
def test_the_image_does_not_depend_on_the_tile_size(tile_size: int) -> None:
    # Every pixel takes the same pairs in the same order whatever the tiling, so its sums are
    # the same bit for bit; gradients are summed per tile first, so they agree to rounding.
    gaussians, camera, background = random_scene(6, 600, 45, 37, torch.float64, 1)
    base, base_grads = _render(CpuTileConfig(), gaussians, camera, background)
    out, grads = _render(CpuTileConfig(tile_size=tile_size), gaussians, camera, background)
    assert torch.equal(out.rgb, base.rgb) and torch.equal(out.alpha, base.alpha)
    _assert_gradients_match(grads, base_grads, torch.float64)


def test_renders_whose_gaussians_all_stop_early_match() -> None:
    # Two hundred opaque Gaussians stacked in front of the camera: every pixel stops early,
    # and backward must start each pixel from the last pair it took.
    n = 200
    gen = torch.Generator().manual_seed(3)
    means = torch.cat((torch.randn(n, 2, generator=gen, dtype=torch.float64) * 0.05,
                       torch.linspace(2, 3, n, dtype=torch.float64)[:, None]), 1)  # fmt: skip
    gaussians = Gaussians(
        means,
        torch.randn(n, 4, generator=gen, dtype=torch.float64),
        torch.tensor([[1.5, 1.2, 0.9]], dtype=torch.float64).repeat(n, 1),
        torch.full((n,), 0.95, dtype=torch.float64),
        torch.rand(n, 3, generator=gen, dtype=torch.float64),
    )
    camera = Camera(30.0, 30.0, 16.0, 12.0, torch.eye(4, dtype=torch.float64), 32, 24)
    background = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)
    want, want_grads = _render(CpuReferenceConfig(), gaussians, camera, background)
    got, got_grads = _render(CpuTileConfig(), gaussians, camera, background)
    # Every pixel ran out of transmittance within the first few Gaussians: the rest draw
    # nothing.
    assert want.contribution is not None and float(want.alpha.detach().min()) > 0.99
    assert bool((want.contribution[n // 2 :] == 0).all())
    _assert_parity(got, want, torch.float64)
    _assert_gradients_match(got_grads, want_grads, torch.float64)


SCREEN_FIELDS = ("means2d", "conics", "opacities", "depths", "colors")


def _projected(
    project_fn: Any, gaussians: Gaussians, camera: Camera, antialiased: bool
) -> tuple[ScreenGaussians, dict[str, Tensor]]:
    """A projection and the gradients of a random weighting of every differentiable field,
    so that each path of the backward (culled rows too) carries some gradient."""
    leaves = {
        name: getattr(gaussians, name).detach().clone().requires_grad_(True) for name in PARAMS
    }
    screen = project_fn(Gaussians(**leaves, sh_degree=gaussians.sh_degree), camera, Guards(),
                        antialiased)  # fmt: skip
    gen = torch.Generator().manual_seed(11)
    loss = sum(
        (getattr(screen, f) * torch.randn(getattr(screen, f).shape, generator=gen,
                                          dtype=torch.float64).to(getattr(screen, f).dtype)).sum()
        for f in SCREEN_FIELDS
    )  # fmt: skip
    loss.backward()  # type: ignore[union-attr]
    return screen, {name: leaf.grad for name, leaf in leaves.items() if leaf.grad is not None}


@pytest.mark.parametrize("antialiased", [False, True], ids=["plain", "antialiased"])
@pytest.mark.parametrize(
    ("seed", "n", "width", "height", "sh_degree"),
    [(0, 400, 97, 61, None), (1, 900, 64, 48, 2), (2, 1500, 130, 70, 3)],
)
def test_compiled_projection_matches_the_pytorch_stage(
    seed: int, n: int, width: int, height: int, sh_degree: int | None, antialiased: bool
) -> None:
    gaussians, camera, _ = random_scene(seed, n, width, height, torch.float64, sh_degree)
    means, quats, scales = (t.clone() for t in (gaussians.means, gaussians.quats, gaussians.scales))
    means[0, 1] = float("nan")  # culled and counted; no gradient may leak from them
    quats[1] = 0.0  # no rotation
    scales[2, 0] = float("inf")
    w2c = camera.world_to_camera.to(torch.float64)
    behind = torch.tensor([0.1, -0.2, -1.0], dtype=torch.float64)  # camera space, z < 0
    means[3] = w2c[:3, :3].T @ (behind - w2c[:3, 3])
    gaussians = replace(gaussians, means=means, quats=quats, scales=scales)
    want, want_grads = _projected(project, gaussians, camera, antialiased)
    got, got_grads = _projected(cpu_tile.project_compiled, gaussians, camera, antialiased)
    assert int(got.num_nonfinite) == int(want.num_nonfinite) == 2
    assert float(want.depths[3].detach()) == 1.0  # culled for depth, its depth replaced by 1
    assert torch.equal(got.visible, want.visible) and bool(want.visible.any())
    for name in (*SCREEN_FIELDS, "extents"):
        diff = float((getattr(got, name) - getattr(want, name)).detach().abs().max())
        assert diff <= 1e-9 * max(float(getattr(want, name).detach().abs().max()), 1), name
    _assert_gradients_match(got_grads, want_grads, torch.float64)
    for grad in got_grads.values():
        assert bool(grad[[0, 2]].eq(0).all()) and bool(grad.isfinite().all())


@pytest.mark.parametrize("antialiased", [False, True], ids=["plain", "antialiased"])
def test_gradcheck_of_the_compiled_projection(antialiased: bool) -> None:
    gaussians, camera, _ = random_scene(5, 6, 16, 12, torch.float64, 1)
    gen = torch.Generator().manual_seed(2)
    weights = [torch.randn(4, generator=gen, dtype=torch.float64) for _ in range(3)]

    def projected(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor) -> Tensor:
        g = Gaussians(means, quats, scales, opacities, gaussians.colors, gaussians.sh_degree)
        s = cpu_tile.project_compiled(g, camera, Guards(), antialiased)
        fields = (s.means2d.sum(1), s.conics @ weights[0][:3], s.opacities, s.depths)
        return torch.stack(fields, 1) @ weights[1] + (s.colors.sum(1) * weights[2][0])

    inputs = tuple(getattr(gaussians, n).detach().clone().requires_grad_(True) for n in PARAMS[:4])
    assert torch.autograd.gradcheck(projected, inputs, atol=1e-7, rtol=1e-5)


@pytest.mark.parametrize(
    ("seed", "n", "width", "height", "tile_size"),
    [
        (0, 300, 97, 61, 16),
        (1, 2000, 33, 129, 8),
        (2, 1200, 130, 70, 4),
        (3, 50, 20, 10, 32),
        (4, 3000, 101, 101, 1),
        (5, 800, 45, 38, 7),  # a tile size that is not a power of two
    ],
)
def test_compiled_binning_gives_the_reference_bins(
    seed: int, n: int, width: int, height: int, tile_size: int
) -> None:
    # Element for element: the same pairs, in the same (tile, then depth) order.
    gaussians, camera, _ = random_scene(seed, n, width, height, torch.float64, 1)
    screen = project(gaussians, camera, Guards())
    want = bin_tiles(screen, width, height, tile_size)
    got = cpu_tile.bin_tiles_compiled(screen, width, height, tile_size)
    assert len(want.gaussian) >= int(screen.visible.sum()) > 0
    for name in ("gaussian", "tile_start", "tile_count"):
        assert torch.equal(getattr(got, name), getattr(want, name)), name


def test_compiled_binning_of_a_view_with_nothing_visible() -> None:
    gaussians, camera, _ = random_scene(8, 50, 20, 10, torch.float32)
    screen = project(gaussians, camera, Guards())
    screen = replace(screen, visible=torch.zeros_like(screen.visible))
    got = cpu_tile.bin_tiles_compiled(screen, 20, 10, 4)
    assert len(got.gaussian) == 0 and int(got.tile_count.sum()) == 0
    assert torch.equal(got.tile_start, torch.zeros(15, dtype=torch.int64))


def test_without_numba_it_says_what_is_missing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(cpu_tile, "cpu_tile_available", lambda: False)
    with pytest.raises(RendererUnavailable, match="needs numba"):
        CpuTileConfig().build()


def test_the_tile_size_follows_the_image_size() -> None:
    # 32-px tiles where the image holds four of them each way, 16 below; a fixed size wins.
    choose = cpu_tile.choose_tile_size
    assert [choose(128, 128), choose(480, 270), choose(800, 800)] == [32, 32, 32]
    assert [choose(100, 100), choose(127, 500), choose(500, 127), choose(1, 1)] == [16] * 4
    gaussians, camera, background = random_scene(7, 2000, 160, 131, torch.float32, 1)
    sizes: list[int] = []
    launch = cpu_tile._launch

    def spy(kernel: Any, threads: int | None, *args: Any) -> None:
        sizes.append(args[2][1])  # layout = (tiles across, tile size, width, height)
        launch(kernel, threads, *args)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(cpu_tile, "_launch", spy)
        auto = CpuTileConfig().build()(gaussians, camera, background)
        fixed = CpuTileConfig(tile_size=16).build()(gaussians, camera, background)
    assert sizes == [32, 16]
    assert torch.equal(auto.rgb, fixed.rgb) and torch.equal(auto.alpha, fixed.alpha)


def test_bad_options_are_refused() -> None:
    with pytest.raises(ConfigError, match="tile-size"):
        CpuTileConfig(tile_size=0)
    with pytest.raises(ConfigError, match="threads"):
        CpuTileConfig(threads=0)


def test_an_empty_view_still_runs_backward() -> None:
    gaussians, camera, background = random_scene(8, 50, 20, 10, torch.float32)
    behind = replace(gaussians, means=gaussians.means.clone().requires_grad_(True))
    w2c = camera.world_to_camera.clone()
    w2c[2, 3] -= 100.0  # everything behind the camera
    out = CpuTileConfig().build()(behind, replace(camera, world_to_camera=w2c), background)
    assert not bool(out.visible.any())
    assert torch.equal(out.rgb, background.expand_as(out.rgb))
    out.rgb.sum().backward()
    assert behind.means.grad is None or bool((behind.means.grad == 0).all())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_the_absolute_gradient_bounds_the_gradient_and_equals_it_on_one_pixel(
    dtype: torch.dtype,
) -> None:
    # Σ|g_p| ≥ |Σ g_p| per axis, with equality where one pixel holds all the terms; and the
    # bound is strict somewhere on a real image (terms of both signs cancel in the gradient).
    for width, height, strict in ((57, 43, True), (1, 1, False)):
        gaussians, camera, background = random_scene(5, 400, width, height, dtype, 1)
        for config in (CpuReferenceConfig(), CpuTileConfig()):
            _, grads = _render(config, gaussians, camera, background)
            grad, absgrad = grads["means2d"].abs(), grads["means2d_absgrad"]
            slack = 1e-12 if dtype == torch.float64 else 1e-5 * float(absgrad.max())
            assert bool((absgrad >= grad - slack).all())
            if strict:
                assert float((absgrad - grad).max()) > 0.1 * float(absgrad.max())
            else:
                assert float((absgrad - grad).abs().max()) <= slack


def test_the_vectorised_exponential_is_the_correctly_rounded_one() -> None:
    # In float32, α = exp(exponent) comes from a polynomial in float64 (libm's expf is a
    # call, which does not vectorise). Rounded to float32 it must be the correctly rounded
    # exponential, the float64 exp of the same float32 rounded once, wherever float32 is
    # normal; and within an ulp of PyTorch's expf, which cpu-reference uses.
    from numba import njit

    from dyngs.renderers.tile_kernels import _exp_nonpositive

    @njit(cache=False)
    def each(x: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
        out = np.empty(x.shape[0], dtype=np.float32)
        for i in range(x.shape[0]):
            out[i] = np.float32(_exp_nonpositive(np.float64(x[i])))
        return out

    rng = np.random.default_rng(0)
    x = np.concatenate([
        -rng.random(1_000_000, dtype=np.float32) * 87,  # every normal exponential
        -rng.random(100_000, dtype=np.float32) * 6,  # where α ≥ 1/255 is decided
        np.array([0.0, -0.0, -1e-30, -1e-7, np.log(1 / 255), np.log(0.99), -87.0]),
    ]).astype(np.float32)  # fmt: skip
    got = each(x)
    want = np.exp(x.astype(np.float64)).astype(np.float32)
    assert np.array_equal(got, want)
    torch_exp = torch.exp(torch.from_numpy(x)).numpy()
    assert np.all(np.abs(got - torch_exp) <= np.spacing(want))
    # Above 0 it is clamped (α is then clamped to alpha_max anyway); far below, it is 0.
    assert each(np.array([0.5, 80.0], dtype=np.float32)).tolist() == [1.0, 1.0]
    assert each(np.array([-200.0, -1e30], dtype=np.float32))[0] < 1e-44


@pytest.mark.parametrize("seed", range(4))
def test_compiled_stable_argsort_is_torchs(seed: int) -> None:
    # Ties (a few distinct values), both signs, subnormals, infinities and a wide range of
    # magnitudes, so that every radix pass and the sign flip matter.
    gen = torch.Generator().manual_seed(seed)
    n = 3000
    pool = torch.tensor([0.0, 1.0, -1.0, 5e-324, -5e-324, 1e300, -1e300, math.inf, -math.inf])
    values = torch.randn(n, generator=gen, dtype=torch.float64) * 10.0 ** torch.randint(
        -30, 30, (n,), generator=gen
    )
    tied = torch.rand(n, generator=gen) < 0.5
    picks = pool[torch.randint(len(pool), (n,), generator=gen)]
    values = torch.where(tied, picks, values)
    values[values == 0] = 0.0  # no −0.0: PyTorch takes it as equal to +0.0
    from dyngs.renderers import tile_kernels

    got = tile_kernels.stable_argsort(values.numpy())
    assert torch.equal(torch.from_numpy(got), torch.argsort(values, stable=True))
    assert len(tile_kernels.stable_argsort(values[:0].numpy())) == 0


def test_compiled_binning_keeps_index_order_among_equal_depths() -> None:
    gaussians, camera, _ = random_scene(5, 400, 40, 30, torch.float64, 1)
    screen = project(gaussians, camera, Guards())
    screen = replace(screen, depths=screen.depths.round(decimals=0))  # a handful of depths
    assert len(screen.depths[screen.visible].unique()) < 10
    want = bin_tiles(screen, 40, 30, 8)
    got = cpu_tile.bin_tiles_compiled(screen, 40, 30, 8)
    for name in ("gaussian", "tile_start", "tile_count"):
        assert torch.equal(getattr(got, name), getattr(want, name)), name


@pytest.mark.parametrize("n", [500, 1000])  # 1000: chunks of the kernel's size and a rest
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gathered_scene_is_the_finite_rows_laid_out_by_column(dtype: torch.dtype, n: int) -> None:
    from dyngs.ops import finite_rows
    from dyngs.renderers import project_kernels

    gen = torch.Generator().manual_seed(3)
    tensors = [torch.randn(n, *shape, generator=gen, dtype=dtype)
               for shape in ((3,), (4,), (3,), (), (16, 3))]  # fmt: skip
    for t in tensors:  # a few NaN and ±Inf entries, anywhere in a row
        flat = t.view(n, -1)
        rows = torch.randint(n, (8,), generator=gen)
        cols = torch.randint(flat.shape[1], (8,), generator=gen)
        flat[rows[:3], cols[:3]] = math.nan
        flat[rows[3:6], cols[3:6]] = math.inf
        flat[rows[6:], cols[6:]] = -math.inf
    want = finite_rows(*tensors)
    assert 0 < int(want.sum()) < n
    got = np.empty(n, dtype=np.bool_)
    scene = np.full((project_kernels.SCENE_ROWS, n), np.nan)
    arrays = tuple(t.reshape(n, -1).numpy() for t in tensors)
    project_kernels.gather_scene(arrays, scene, got)
    assert torch.equal(torch.from_numpy(got), want)
    columns = torch.cat([t.reshape(n, -1) for t in tensors[:4]], 1).double()
    assert torch.equal(torch.from_numpy(scene).T, torch.where(want[:, None], columns, 0.0))
    none = np.empty(0, dtype=np.bool_)
    empty = tuple(a[:0] for a in arrays)
    project_kernels.gather_scene(empty, np.empty((project_kernels.SCENE_ROWS, 0)), none)

"""`cuda-tile` against `cpu-reference` on the same GPU, and its refusal to run where it
cannot. Parity tests skip, saying why, on machines without CUDA or gsplat."""

from __future__ import annotations

import importlib.util

import pytest
import torch

from dyngs.cli import main
from dyngs.renderers import (
    CpuReferenceConfig,
    CudaTileConfig,
    RendererUnavailable,
    default_renderer,
)
from dyngs.renderers.cuda_tile import cuda_tile_available
from dyngs.types import Gaussians
from tests.renderers.scenes import random_scene

HAS_CUDA = torch.cuda.is_available()
HAS_GSPLAT = importlib.util.find_spec("gsplat") is not None
needs_gpu = pytest.mark.skipif(
    not (HAS_CUDA and HAS_GSPLAT),
    reason="parity with gsplat needs a CUDA device and `pip install dyngs[cuda]`",
)


@pytest.mark.skipif(HAS_CUDA, reason="this machine has CUDA")
def test_without_cuda_it_says_what_is_missing() -> None:
    with pytest.raises(RendererUnavailable, match="needs a CUDA device"):
        CudaTileConfig().build()
    # Without CUDA the default is the compiled CPU rasterizer.
    assert not isinstance(default_renderer(), CudaTileConfig)
    assert not cuda_tile_available()


@pytest.mark.skipif(HAS_CUDA, reason="this machine has CUDA")
def test_cli_refuses_cuda_tile_in_one_line(capsys: pytest.CaptureFixture[str], tmp_path) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(SystemExit) as exit_info:
        main(
            ["hexplane-4dgs", "renderer:cuda-tile", "--data", "demo", "--output-dir", str(tmp_path)]
        )
    assert exit_info.value.code == 2
    out = capsys.readouterr()
    text = (out.out + out.err).strip()
    assert "cuda-tile needs a CUDA device" in text and len(text.splitlines()) == 1


@pytest.mark.skipif(not HAS_CUDA or HAS_GSPLAT, reason="needs CUDA without gsplat")
def test_without_gsplat_it_says_what_is_missing() -> None:
    with pytest.raises(RendererUnavailable, match="pip install dyngs\\[cuda\\]"):
        CudaTileConfig().build()


def _boundary_band(alpha: torch.Tensor) -> torch.Tensor:
    """Pixels next to a change of coverage: where the two renderers' integer and exact
    extents can disagree by one pixel."""
    covered = (alpha[..., 0] > 0).float()[None, None]
    pooled_max = torch.nn.functional.max_pool2d(covered, 3, 1, 1)
    pooled_min = -torch.nn.functional.max_pool2d(-covered, 3, 1, 1)
    return (pooled_max != pooled_min)[0, 0]


@needs_gpu
@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("packed", [False, True])
def test_images_match_the_reference(seed: int, antialiased: bool, packed: bool) -> None:
    gaussians, camera, background = random_scene(
        200 + seed, 400, 97, 61, torch.float32, sh_degree=seed % 4
    )
    # Opacities ≤ 0.99 keep gsplat's 0.999 α clamp out of play (see cuda_tile.py).
    gaussians.opacities.clamp_(max=0.99)
    gaussians = gaussians.to("cuda")
    camera, background = camera.to("cuda"), background.cuda()
    fast = CudaTileConfig(antialiased=antialiased, packed=packed).build()(
        gaussians, camera, background
    )
    slow = CpuReferenceConfig(antialiased=antialiased).build()(gaussians, camera, background)
    band = _boundary_band(slow.alpha) | _boundary_band(fast.alpha)
    for a, b in ((fast.rgb, slow.rgb), (fast.alpha, slow.alpha)):
        diff = (a - b).abs().amax(dim=-1)
        assert float(diff[~band].max()) <= 1e-4
        # Boundary-band disagreements stay rare: at most 2 % of the image.
        assert float((diff[band] > 1e-4).float().sum()) <= 0.02 * diff.numel()


@needs_gpu
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("packed", [False, True])
def test_gradients_match_the_reference(seed: int, packed: bool) -> None:
    base, camera, background = random_scene(300 + seed, 150, 64, 48, torch.float32, sh_degree=1)
    base.opacities.clamp_(max=0.99)
    camera, background = camera.to("cuda"), background.cuda()
    weights = torch.rand(48, 64, 3, generator=torch.Generator().manual_seed(seed)).cuda()
    grads = []
    for config in (CudaTileConfig(packed=packed), CpuReferenceConfig()):
        g = base.to("cuda")
        leaves = [
            t.clone().requires_grad_(True)
            for t in (g.means, g.quats, g.scales, g.opacities, g.colors)
        ]
        means, quats, scales, opacities, colors = leaves
        out = config.build()(
            Gaussians(means, quats, scales, opacities, colors, 1), camera, background
        )
        (out.rgb * weights).sum().backward()
        # The 2D means' gradient too: densification reads it (and nothing else does).
        grads.append([t.grad for t in leaves] + [out.means2d.grad])
    for name, fast, slow in zip(
        ("means", "quats", "scales", "opacities", "colors", "means2d"), *grads, strict=True
    ):
        assert fast is not None and slow is not None, name
        scale = slow.abs().max().clamp_min(1e-12)
        relative = ((fast - slow).abs() / scale).flatten()
        # Relative 1e-3 for all but a bounded share (boundary-band pairs), stated here: 2 %.
        assert float((relative > 1e-3).float().mean()) <= 0.02, name


@needs_gpu
@pytest.mark.parametrize("packed", [False, True])
def test_absolute_gradients_match_the_reference(packed: bool) -> None:
    # Densification reads them by default: gsplat's `.absgrad`, copied out by a hook.
    base, camera, background = random_scene(310, 150, 64, 48, torch.float32, sh_degree=1)
    base.opacities.clamp_(max=0.99)
    camera, background = camera.to("cuda"), background.cuda()
    weights = torch.rand(48, 64, 3, generator=torch.Generator().manual_seed(5)).cuda()
    found = []
    for config in (CudaTileConfig(packed=packed), CpuReferenceConfig()):
        g = base.to("cuda")
        means = g.means.clone().requires_grad_(True)
        out = config.build()(
            Gaussians(means, g.quats, g.scales, g.opacities, g.colors, 1), camera, background
        )
        (out.rgb * weights).sum().backward()
        assert out.means2d_absgrad is not None
        found.append(out.means2d_absgrad.double())
    fast, slow = found
    relative = ((fast - slow).abs() / slow.abs().max()).flatten()
    assert float(slow.abs().max()) > 0
    assert float((relative > 1e-3).float().mean()) <= 0.02


class _StandInSplat(torch.autograd.Function):
    """A stand-in for gsplat's rasterize step, for the plumbing around it: every pixel is
    a fixed weighted sum of the 2D means it is handed, and backward hangs an absolute
    gradient on them as `.absgrad`, as gsplat's does (here |grad| + 1, to be told apart)."""

    @staticmethod
    def forward(ctx, means2d: torch.Tensor, weights: torch.Tensor, shape: tuple[int, ...]):  # type: ignore[no-untyped-def, override]
        ctx.save_for_backward(means2d, weights)
        return ((means2d * weights).sum() * torch.ones(shape, dtype=means2d.dtype)).clone()

    @staticmethod
    def backward(ctx, grad):  # type: ignore[no-untyped-def, override]
        means2d, weights = ctx.saved_tensors
        v_means2d = grad.sum() * weights
        means2d.absgrad = v_means2d.abs() + 1
        return v_means2d, None, None


def _stand_in_rasterization(**kw: object):  # type: ignore[no-untyped-def]
    """gsplat's `rasterization` in shape and in how its 2D means reach the loss: a pinhole
    projection, packed mode listing every other Gaussian, the pixels from `_StandInSplat`."""
    means, viewmats, Ks = kw["means"], kw["viewmats"], kw["Ks"]
    assert isinstance(means, torch.Tensor) and isinstance(viewmats, torch.Tensor)
    assert isinstance(Ks, torch.Tensor)
    n, width, height = len(means), int(kw["width"]), int(kw["height"])  # type: ignore[call-overload]
    cam = means @ viewmats[0, :3, :3].T + viewmats[0, :3, 3]
    means2d = ((cam[:, :2] / cam[:, 2:]) * Ks[0, [0, 1], [0, 1]] + Ks[0, :2, 2])[None]
    radii = torch.ones(1, n, 2, dtype=torch.int32)
    meta: dict[str, torch.Tensor] = {}
    if kw["packed"]:
        ids = torch.arange(0, n, 2)
        means2d, radii = means2d[0, ids], radii[0, ids]
        meta["gaussian_ids"] = ids
    weights = torch.rand(means2d.shape, generator=torch.Generator().manual_seed(3))
    weights = weights.to(means2d.dtype)
    rgbd = _StandInSplat.apply(means2d, weights, (1, height, width, 4))
    alpha = torch.zeros(1, height, width, 1, dtype=means.dtype)
    meta.update(means2d=means2d, radii=radii)
    return rgbd, alpha, meta


@pytest.mark.parametrize("packed", [False, True])
def test_screen_gradients_reach_densification(packed: bool) -> None:
    # Densification reads `out.means2d.grad` and `out.means2d_absgrad` after backward.
    # gsplat rasterizes from its own 2D means, so a view of them handed out never got a
    # gradient, and no run densified on a GPU (2026-11-27); the gradient-parity tests did
    # not see it, as they compare the parameters' gradients. This drives cuda-tile's whole
    # call around a stand-in for gsplat, on any machine.
    from dyngs.renderers.base import Guards
    from dyngs.renderers.cuda_tile import CudaTileRenderer

    g, camera, background = random_scene(11, 9, 16, 12, torch.float32, sh_degree=0)
    g.means.requires_grad_(True)
    renderer = object.__new__(CudaTileRenderer)
    renderer.config, renderer.guards = CudaTileConfig(packed=packed), Guards()
    handed: list[torch.Tensor] = []

    def rasterization(**kw: object):  # type: ignore[no-untyped-def]
        rgbd, alpha, meta = _stand_in_rasterization(**kw)
        meta["means2d"].retain_grad()
        handed.append(meta["means2d"])
        return rgbd, alpha, meta

    renderer._rasterization = rasterization
    out = renderer(g, camera, background)
    assert out.means2d.grad is None and out.means2d_absgrad is not None
    (out.rgb.sum() * 0.5).backward()
    full = handed[0]
    assert full.grad is not None and bool((full.grad != 0).any())
    rows = torch.arange(9) if not packed else torch.arange(0, 9, 2)
    want = torch.zeros(9, 2).index_copy(0, rows, full.grad.reshape(-1, 2))
    want_abs = torch.zeros(9, 2).index_copy(0, rows, full.absgrad.reshape(-1, 2))  # type: ignore[attr-defined]
    assert out.means2d.grad is not None
    assert torch.equal(out.means2d.grad, want)
    assert torch.equal(out.means2d_absgrad, want_abs)
    assert torch.equal(
        out.means2d.detach(), torch.zeros(9, 2).index_copy(0, rows, full.detach().reshape(-1, 2))
    )
    assert g.means.grad is not None and bool((g.means.grad != 0).any())


def test_an_empty_scene_is_the_background_without_calling_gsplat() -> None:
    # gsplat's projection stops the process (SIGFPE, seen on an H200) when handed zero
    # Gaussians, so cuda-tile draws an empty scene itself. That path needs no GPU: it must
    # equal cpu-reference's empty image and keep backward running.
    from dyngs.renderers.cuda_tile import CudaTileRenderer
    from dyngs.renderers.stages import prepare

    full, camera, background = random_scene(7, 5, 13, 9, torch.float32, sh_degree=1)
    means, quats, scales, opacities, colors = leaves = [
        t[:0].clone().requires_grad_(True)
        for t in (full.means, full.quats, full.scales, full.opacities, full.colors)
    ]
    empty = Gaussians(means, quats, scales, opacities, colors, sh_degree=1)
    got = CudaTileRenderer._background_only(empty, camera, background, prepare(empty, camera))
    want = CpuReferenceConfig().build()(empty, camera, background)
    for name in ("rgb", "alpha", "depth"):
        assert torch.equal(getattr(got, name).detach(), getattr(want, name).detach()), name
    assert got.means2d.shape == (0, 2) and got.radii.shape == (0, 2) and got.visible.shape == (0,)
    assert int(got.num_nonfinite) == 0
    (got.rgb.sum() + got.alpha.sum() + got.depth.sum()).backward()
    assert all(leaf.grad is not None and leaf.grad.numel() == 0 for leaf in leaves)

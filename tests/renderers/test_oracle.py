"""Checks of the brute-force oracle itself against numbers computed by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dyngs.types import Camera, Gaussians
from tests.renderers.oracle import C0, C1, C2, C3, render_oracle, sh_basis

F64 = torch.float64
SIZE = 11
CENTRE = 5  # pixel (5, 5) has its centre at (5.5, 5.5), the principal point
FOCAL = 100.0


def make_camera(world_to_camera: torch.Tensor | None = None) -> Camera:
    w2c = torch.eye(4, dtype=F64) if world_to_camera is None else world_to_camera
    return Camera(FOCAL, FOCAL, SIZE / 2, SIZE / 2, w2c, SIZE, SIZE)


def make_gaussians(means, scales, opacities, colors, quats=None, sh_degree=None) -> Gaussians:
    means = torch.tensor(means, dtype=F64).reshape(-1, 3)
    n = means.shape[0]
    scales = torch.tensor(scales, dtype=F64).reshape(n, 3)
    quats = torch.tensor([[1.0, 0, 0, 0]] * n if quats is None else quats, dtype=F64).reshape(n, 4)
    return Gaussians(
        means,
        quats,
        scales,
        torch.tensor(opacities, dtype=F64).reshape(n),
        torch.tensor(colors, dtype=F64),
        sh_degree,
    )


BG = torch.tensor([0.1, 0.2, 0.3], dtype=F64)


@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("opacity", [0.8, 1.0])
def test_single_isotropic_gaussian(antialiased: bool, opacity: float) -> None:
    z, s = 2.0, 0.01
    var = (FOCAL * s / z) ** 2  # projected variance in px²: σ_px = f·s/z = 0.5
    g = make_gaussians([0, 0, z], [s, s, s], [opacity], [[0.9, 0.5, 0.1]])
    out = render_oracle(g, make_camera(), BG, antialiased=antialiased)
    filter_px2 = 0.1 if antialiased else 0.3  # Mip-Splatting's 2D filter; 3DGS's dilation
    o = opacity * (var / (var + filter_px2) if antialiased else 1.0)  # sqrt(det Σ2 / det Σ2d)
    a_centre = min(0.99, o)
    a_side = min(0.99, o * math.exp(-0.5 * 1.0 / (var + filter_px2)))
    a_diag = min(0.99, o * math.exp(-0.5 * 2.0 / (var + filter_px2)))
    assert out.alpha[CENTRE, CENTRE, 0].item() == pytest.approx(a_centre, rel=1e-14)
    for di, dj in [(0, 1), (0, -1), (1, 0), (-1, 0)]:
        assert out.alpha[CENTRE + di, CENTRE + dj, 0].item() == pytest.approx(a_side, rel=1e-12)
    assert out.alpha[CENTRE + 1, CENTRE + 1, 0].item() == pytest.approx(a_diag, rel=1e-12)
    expected_rgb = a_centre * torch.tensor([0.9, 0.5, 0.1], dtype=F64) + (1 - a_centre) * BG
    torch.testing.assert_close(out.rgb[CENTRE, CENTRE], expected_rgb, rtol=1e-13, atol=1e-14)
    assert out.depth[CENTRE, CENTRE, 0].item() == pytest.approx(z, rel=1e-14)
    assert out.touches.tolist() == [True]
    assert out.rgb.dtype == F64 and out.rgb.shape == (SIZE, SIZE, 3)
    assert out.alpha.shape == out.depth.shape == (SIZE, SIZE, 1)
    assert out.fragile.shape == (SIZE, SIZE)


def test_two_gaussians_composite_in_depth_order() -> None:
    c1, c2 = [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]
    near = ([0, 0, 2.0], [0.02] * 3, 0.6, c1)
    far = ([0, 0, 4.0], [0.04] * 3, 0.7, c2)
    outs = []
    for first, second in [(near, far), (far, near)]:
        g = make_gaussians(
            [first[0], second[0]],
            [first[1], second[1]],
            [first[2], second[2]],
            [first[3], second[3]],
        )
        outs.append(render_oracle(g, make_camera(), BG))
    a1, a2 = 0.6, 0.7  # both centred on the pixel, so α = opacity there
    expected = (
        a1 * torch.tensor(c1, dtype=F64)
        + (1 - a1) * a2 * torch.tensor(c2, dtype=F64)
        + (1 - a1) * (1 - a2) * BG
    )
    torch.testing.assert_close(outs[0].rgb[CENTRE, CENTRE], expected, rtol=1e-13, atol=1e-14)
    w1, w2 = a1, (1 - a1) * a2
    assert outs[0].alpha[CENTRE, CENTRE, 0].item() == pytest.approx(w1 + w2, rel=1e-14)
    assert outs[0].depth[CENTRE, CENTRE, 0].item() == pytest.approx((w1 * 2 + w2 * 4) / (w1 + w2))
    for name in ["rgb", "alpha", "depth", "fragile"]:
        assert torch.equal(getattr(outs[0], name), getattr(outs[1], name)), name


def test_equal_depths_keep_index_order() -> None:
    c1, c2 = [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]
    g = make_gaussians([[0, 0, 2.0]] * 2, [[0.02] * 3] * 2, [0.5, 0.5], [c1, c2])
    out = render_oracle(g, make_camera(), torch.zeros(3, dtype=F64))
    expected = torch.tensor([0.5, 0.0, 0.25], dtype=F64)  # the first one listed is in front
    torch.testing.assert_close(out.rgb[CENTRE, CENTRE], expected, rtol=1e-14, atol=0.0)


@pytest.mark.parametrize("z", [-2.0, 0.0, 0.01, 2e10])
def test_gaussian_outside_near_far_draws_nothing(z: float) -> None:
    g = make_gaussians([0, 0, z], [0.5] * 3, [0.9], [[1.0, 1.0, 1.0]])
    out = render_oracle(g, make_camera(), BG)
    assert torch.equal(out.rgb, BG.expand(SIZE, SIZE, 3))
    assert not out.alpha.any() and not out.depth.any() and not out.touches.any()


def test_empty_scene() -> None:
    g = Gaussians(
        torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3)
    )
    out = render_oracle(g, make_camera(), BG)
    assert torch.equal(out.rgb, BG.expand(SIZE, SIZE, 3))
    assert not out.alpha.any() and not out.depth.any() and out.touches.shape == (0,)


def test_non_finite_gaussian_is_dropped() -> None:
    good = ([0, 0, 2.0], [0.02] * 3, 0.6, [1.0, 0.0, 0.0])
    means, scales, opac, cols = zip(good, good, strict=True)
    only = render_oracle(make_gaussians(*good[:3], [good[3]]), make_camera(), BG)
    for field, index in [
        ("means", 0),
        ("quats", 2),
        ("scales", 1),
        ("opacities", None),
        ("colors", 2),
    ]:
        g = make_gaussians(list(means), list(scales), list(opac), list(cols))
        bad = getattr(g, field)
        bad[0] = float("nan") if index is None else bad[0]
        if index is not None:
            bad[0, index] = float("inf")
        out = render_oracle(g, make_camera(), BG)
        assert torch.equal(out.rgb, only.rgb), field
        assert out.touches.tolist() == [False, True], field


def test_zero_and_unnormalised_quaternions() -> None:
    scales = [0.01, 0.03, 0.02]
    outs = [
        render_oracle(
            make_gaussians([0.01, -0.02, 2.0], scales, [0.8], [[1.0, 1, 1]], quats=[q]),
            make_camera(),
            BG,
        )
        for q in ([1.0, 0, 0, 0], [0.0, 0, 0, 0], [3e-30, 0, 0, 0], [5e20, 0, 0, 0])
    ]
    for out in outs[1:]:
        torch.testing.assert_close(out.rgb, outs[0].rgb, rtol=1e-14, atol=1e-15)
    # A quarter turn about the optical axis swaps the x and y extents: the image transposes.
    half = math.sqrt(0.5)
    rotated = render_oracle(
        make_gaussians([0, 0, 2.0], scales, [0.8], [[1.0, 1, 1]], quats=[[half, 0, 0, half]]),
        make_camera(),
        BG,
    )
    swapped = render_oracle(
        make_gaussians([0, 0, 2.0], [0.03, 0.01, 0.02], [0.8], [[1.0, 1, 1]]), make_camera(), BG
    )
    torch.testing.assert_close(rotated.alpha, swapped.alpha, rtol=1e-12, atol=1e-15)


def test_sh_constants_match_3dgs() -> None:
    assert C0 == pytest.approx(0.28209479177387814, rel=1e-15)
    assert C1 == pytest.approx(0.4886025119029199, rel=1e-15)
    expected_c2 = [
        1.0925484305920792,
        -1.0925484305920792,
        0.31539156525252005,
        -1.0925484305920792,
        0.5462742152960396,
    ]
    expected_c3 = [
        -0.5900435899266435,
        2.890611442640554,
        -0.4570457994644658,
        0.3731763325901154,
        -0.4570457994644658,
        1.445305721320277,
        -0.5900435899266435,
    ]
    assert C2 == pytest.approx(expected_c2, rel=1e-15)
    assert C3 == pytest.approx(expected_c3, rel=1e-15)


def test_sh_basis_is_orthonormal() -> None:
    # Gauss–Legendre in cos θ and a uniform grid in φ integrate these degree ≤ 6 products exactly.
    mu, w_mu = np.polynomial.legendre.leggauss(12)
    n_phi = 24
    phi = np.arange(n_phi) * 2 * np.pi / n_phi
    mu_g, phi_g = np.meshgrid(mu, phi, indexing="ij")
    sin_t = np.sqrt(1 - mu_g**2)
    dirs = np.stack([sin_t * np.cos(phi_g), sin_t * np.sin(phi_g), mu_g], -1).reshape(-1, 3)
    weights = torch.tensor((w_mu[:, None] * np.full(n_phi, 2 * np.pi / n_phi)).reshape(-1))
    basis = sh_basis(torch.tensor(dirs), 3)  # [M, 16]
    gram = basis.T @ (weights[:, None] * basis)
    torch.testing.assert_close(gram, torch.eye(16, dtype=F64), rtol=0.0, atol=1e-13)


def test_sh_colours() -> None:
    # Degree 0: colour = c·Y_00 + 0.5, clamped below at 0 only.
    dc = [[[0.3, -0.2, -2.0]]]
    g = make_gaussians([0, 0, 2.0], [0.02] * 3, [0.5], dc, sh_degree=0)
    out = render_oracle(g, make_camera(), torch.zeros(3, dtype=F64))
    expected = [0.3 * C0 + 0.5, -0.2 * C0 + 0.5, 0.0]
    assert (2 * out.rgb[CENTRE, CENTRE]).tolist() == pytest.approx(expected, rel=1e-14)
    assert 0.28209479177387814 == pytest.approx(C0, rel=1e-15)
    # Degree 1, camera centre at world (0, 0, -5): the view direction is +z, so only the
    # m = 0 coefficient (index 2) counts, with weight +C1.
    w2c = torch.eye(4, dtype=F64)
    w2c[2, 3] = 5.0
    coeffs = torch.zeros(1, 4, 3, dtype=F64)
    coeffs[0, 0] = torch.tensor([0.1, 0.2, 0.3])
    coeffs[0, 1] = coeffs[0, 3] = torch.tensor([7.0, 7.0, 7.0])  # ∝ y and x: zero on the axis
    coeffs[0, 2] = torch.tensor([0.5, -0.5, 1.0])
    g = make_gaussians([0, 0, -3.0], [0.02] * 3, [0.5], coeffs.tolist(), sh_degree=1)
    out = render_oracle(g, make_camera(w2c), torch.zeros(3, dtype=F64))
    expected = (coeffs[0, 0] * C0 + coeffs[0, 2] * C1 + 0.5).clamp_min(0).tolist()
    assert (2 * out.rgb[CENTRE, CENTRE]).tolist() == pytest.approx(expected, rel=1e-14)
    assert out.depth[CENTRE, CENTRE, 0].item() == pytest.approx(2.0, rel=1e-14)


COLS = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
COLS_T = torch.tensor(COLS, dtype=F64)


def three_on_axis(opacities: list[float]):
    g = make_gaussians(
        [[0, 0, 1.0], [0, 0, 2.0], [0, 0, 3.0]],
        [[0.01] * 3, [0.02] * 3, [0.03] * 3],
        opacities,
        COLS,
    )
    return render_oracle(g, make_camera(), BG)


def test_early_stop_boundary_three_at_099() -> None:
    # Opacity 1 is clamped to α = 0.99. In float64 1 − 0.99 = 0.010000000000000009, so the
    # transmittance after two is 1.0000000000000018e-4: not < 1e-4, the second is drawn; the
    # third would give ~1e-6 < 1e-4, so the pixel stops there. This decision is fragile.
    t1 = 1 - 0.99
    t2 = t1 * (1 - 0.99)
    assert t2 >= 1e-4 and t2 * (1 - 0.99) < 1e-4
    out = three_on_axis([1.0, 1.0, 1.0])
    expected = 0.99 * COLS_T[0] + t1 * 0.99 * COLS_T[1] + t2 * BG
    torch.testing.assert_close(out.rgb[CENTRE, CENTRE], expected, rtol=1e-14, atol=1e-16)
    assert out.alpha[CENTRE, CENTRE, 0].item() == pytest.approx(1 - 1e-4, rel=1e-14)
    assert out.fragile[CENTRE, CENTRE]
    assert out.touches.tolist() == [True, True, True]


def test_early_stop_unambiguous() -> None:
    # α = 0.99, 0.98, 0.99: T = 0.01, then 2e-4 (drawn), then 2e-6 (stop): the third is not drawn.
    out = three_on_axis([0.99, 0.98, 0.99])
    expected = 0.99 * COLS_T[0] + 0.01 * 0.98 * COLS_T[1] + 2e-4 * BG
    torch.testing.assert_close(out.rgb[CENTRE, CENTRE], expected, rtol=1e-12, atol=1e-15)
    assert out.alpha[CENTRE, CENTRE, 0].item() == pytest.approx(0.9998, rel=1e-14)
    assert not out.fragile[CENTRE, CENTRE]
    # α = 0.99, 0.98, 0.6: T = 0.01, 2e-4, then 8e-5 < 1e-4, so the pixel stops at the third.
    out = three_on_axis([0.99, 0.98, 0.6])
    expected = 0.99 * COLS_T[0] + 0.01 * 0.98 * COLS_T[1] + 2e-4 * BG
    torch.testing.assert_close(out.rgb[CENTRE, CENTRE], expected, rtol=1e-12, atol=1e-15)
    assert not out.fragile[CENTRE, CENTRE]
    # α = 0.99, 0.98, 0.4: the third gives 1.2e-4 ≥ 1e-4 and is drawn.
    out = three_on_axis([0.99, 0.98, 0.4])
    expected = 0.99 * COLS_T[0] + 0.01 * 0.98 * COLS_T[1] + 2e-4 * 0.4 * COLS_T[2] + 1.2e-4 * BG
    torch.testing.assert_close(out.rgb[CENTRE, CENTRE], expected, rtol=1e-12, atol=1e-15)
    assert out.alpha[CENTRE, CENTRE, 0].item() == pytest.approx(1 - 1.2e-4, rel=1e-14)
    assert not out.fragile[CENTRE, CENTRE]
    # α is clamped to 0.99, so at the centre opacity 0.995 behaves exactly like 0.99.
    clamped = three_on_axis([0.995, 0.98, 0.6]).rgb[CENTRE, CENTRE]
    assert torch.equal(clamped, three_on_axis([0.99, 0.98, 0.6]).rgb[CENTRE, CENTRE])


def test_alpha_threshold() -> None:
    # α exactly 1/255 at the centre: drawn, and fragile.
    g = make_gaussians([0, 0, 2.0], [0.01] * 3, [1 / 255], [[1.0, 1.0, 1.0]])
    out = render_oracle(g, make_camera(), torch.zeros(3, dtype=F64))
    assert out.alpha[CENTRE, CENTRE, 0].item() == pytest.approx(1 / 255, rel=1e-15)
    assert out.alpha.count_nonzero() == 1 and out.fragile[CENTRE, CENTRE] and out.touches.all()
    # Just below, outside the window: nothing drawn, not fragile, touches nothing.
    g.opacities[0] = (1 / 255) * (1 - 1e-3)
    out = render_oracle(g, make_camera(), torch.zeros(3, dtype=F64))
    assert not out.alpha.any() and not out.fragile.any() and not out.touches.any()

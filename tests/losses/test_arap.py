"""k nearest neighbours, falloff weights and the local-rigidity loss."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import dyngs.neighbors as neighbors_module
from dyngs.losses.arap import arap_loss, neighbor_weights, safe_norm
from dyngs.neighbors import knn


def _points(n: int, seed: int = 0, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    return torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def _brute_force(points: torch.Tensor, k: int) -> torch.Tensor:
    d = (points[:, None] - points[None]).square().sum(-1)
    d.fill_diagonal_(math.inf)
    return d.argsort(dim=1, stable=True)[:, :k]


def _distances(points: torch.Tensor, neighbors: torch.Tensor) -> torch.Tensor:
    return (points[:, None] - points[neighbors]).norm(dim=-1)


def _rotation(seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))  # Haar-random orthogonal
    if torch.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


# ---------------------------------------------------------------- knn


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_knn_agrees_with_brute_force(dtype: torch.dtype) -> None:
    points = _points(300, dtype=dtype)
    torch.testing.assert_close(knn(points, 6), _brute_force(points, 6))


@pytest.mark.parametrize("layout", ["uniform", "clusters", "plane", "outliers"])
def test_knn_many_octree_leaves(layout: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Small leaves exercise the octree cut, sibling runs and the search radius."""
    monkeypatch.setattr(neighbors_module, "KNN_LEAF_SIZE", 16)
    gen = torch.Generator().manual_seed(1)
    if layout == "uniform":
        points = torch.rand(800, 3, generator=gen, dtype=torch.float64)
    elif layout == "clusters":  # far apart: the Morton grid must still resolve each one
        points = torch.randn(800, 3, generator=gen, dtype=torch.float64) * 1e-3
        points[400:] += 100.0
    elif layout == "plane":
        points = torch.rand(800, 3, generator=gen, dtype=torch.float64)
        points[:, 2] = 0.5
    else:
        points = torch.rand(800, 3, generator=gen, dtype=torch.float64)
        points[:20] *= 1e3
    neighbors = knn(points, 8)
    assert neighbors.shape == (800, 8)
    torch.testing.assert_close(neighbors, _brute_force(points, 8))


def test_knn_coincident_points_are_neighbours_and_self_is_excluded() -> None:
    base = _points(40)
    points = torch.cat([base, base, base])  # every point three times
    neighbors = knn(points, 4)
    rows = torch.arange(len(points))[:, None]
    assert not (neighbors == rows).any()
    d = _distances(points, neighbors)
    assert (d[:, :2] == 0).all()  # the two copies come first
    torch.testing.assert_close(d, _distances(points, _brute_force(points, 4)))


def test_knn_with_no_more_points_than_k_returns_all_others() -> None:
    points = _points(4)
    neighbors = knn(points, 8)
    assert neighbors.shape == (4, 3)
    for i in range(4):
        assert sorted(neighbors[i].tolist()) == [j for j in range(4) if j != i]
    assert knn(_points(1), 8).shape == (1, 0)
    assert knn(torch.zeros(0, 3), 8).shape == (0, 0)
    assert knn(points, 0).shape == (4, 0)


def test_knn_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="N, 3"):
        knn(torch.zeros(5, 2), 2)
    with pytest.raises(ValueError, match="finite"):
        knn(torch.tensor([[0.0, 0.0, 0.0], [math.nan, 0.0, 0.0], [1.0, 1.0, 1.0]]), 1)


@settings(max_examples=25, deadline=None)
@given(n=st.integers(2, 60), k=st.integers(1, 10), seed=st.integers(0, 2**16))
def test_knn_property(n: int, k: int, seed: int) -> None:
    points = _points(n, seed)
    expected = _brute_force(points, min(k, n - 1))
    torch.testing.assert_close(_distances(points, knn(points, k)), _distances(points, expected))


# ---------------------------------------------------------------- weights


def test_neighbor_weights_gaussian_falloff() -> None:
    points = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]], dtype=torch.float64)
    neighbors = torch.tensor([[1, 2], [0, 2], [0, 1]])
    w = neighbor_weights(points, neighbors, scale=2.0)
    expected = torch.tensor(
        [
            [math.exp(-1 / 4), math.exp(-4 / 4)],
            [math.exp(-1 / 4), math.exp(-5 / 4)],
            [math.exp(-4 / 4), math.exp(-5 / 4)],
        ],
        dtype=torch.float64,
    )
    torch.testing.assert_close(w, expected)
    with pytest.raises(ValueError, match="scale"):
        neighbor_weights(points, neighbors, scale=math.nan)


# ---------------------------------------------------------------- arap loss


def _setup(n: int = 200, k: int = 8) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    points = _points(n)
    neighbors = knn(points, k)
    return points, neighbors, neighbor_weights(points, neighbors, scale=1.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rigid_motion_costs_nothing(seed: int) -> None:
    points, neighbors, weights = _setup()
    moved = points @ _rotation(seed).T + torch.tensor([3.0, -1.0, 0.5], dtype=torch.float64)
    assert arap_loss(points, moved, neighbors, weights).item() == pytest.approx(0.0, abs=1e-12)


def test_uniform_stretch_costs_the_weighted_mean_change() -> None:
    points, neighbors, weights = _setup()
    # Scaling by 1.1 lengthens every pair by 0.1·d: the loss is the weighted mean of 0.1·d.
    d = _distances(points, neighbors)
    expected = (weights * 0.1 * d).sum() / weights.sum()
    loss = arap_loss(points, 1.1 * points, neighbors, weights)
    assert loss.item() > 0
    torch.testing.assert_close(loss, expected, rtol=1e-6, atol=0)


def test_hand_computed_pair() -> None:
    a = torch.tensor([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0]], dtype=torch.float64)
    b = torch.tensor([[0.0, 0.0, 0.0], [6.0, 8.0, 0.0]], dtype=torch.float64)
    neighbors = torch.tensor([[1], [0]])
    weights = torch.tensor([[1.0], [3.0]], dtype=torch.float64)
    # Both pairs change from 5 to 10.
    assert arap_loss(a, b, neighbors, weights).item() == pytest.approx(5.0, rel=1e-9)


def test_coincident_neighbours_have_finite_value_and_gradient() -> None:
    base = _points(30)
    pos_a = torch.cat([base, base]).requires_grad_()  # each point has a twin at distance 0
    pos_b = (torch.cat([base, base]) + 0.1 * _points(60, seed=3)).requires_grad_()
    neighbors = knn(pos_a.detach(), 4)
    weights = neighbor_weights(pos_a.detach(), neighbors, scale=1.0)
    loss = arap_loss(pos_a, pos_b, neighbors, weights)
    loss.backward()
    assert torch.isfinite(loss) and loss.item() > 0
    for pos in (pos_a, pos_b):
        assert pos.grad is not None and torch.isfinite(pos.grad).all()


def test_coincident_at_both_times_gives_zero_and_no_nan() -> None:
    pos = torch.zeros(5, 3, requires_grad=True)  # every pair at distance 0
    neighbors = knn(pos.detach(), 4)
    weights = torch.ones(5, 4)
    loss = arap_loss(pos, pos * 1.0, neighbors, weights)
    loss.backward()
    assert loss.item() == 0.0
    assert pos.grad is not None and torch.isfinite(pos.grad).all()


def test_safe_norm_gradient_at_zero() -> None:
    v = torch.zeros(2, 3, dtype=torch.float64, requires_grad=True)
    safe_norm(v).sum().backward()
    assert v.grad is not None and (v.grad == 0).all()
    assert safe_norm(torch.tensor([3.0, 4.0], dtype=torch.float64)).item() == pytest.approx(5.0)


def test_gradients_reach_both_times_and_the_weights() -> None:
    points, neighbors, weights = _setup(50, 4)
    pos_a = points.clone().requires_grad_()
    pos_b = (points + 0.05 * _points(50, seed=9)).requires_grad_()
    weights = weights.clone().requires_grad_()
    arap_loss(pos_a, pos_b, neighbors, weights).backward()
    for t in (pos_a, pos_b, weights):
        assert t.grad is not None and torch.isfinite(t.grad).all() and t.grad.abs().sum() > 0


def test_no_pairs_costs_nothing() -> None:
    pos = _points(1).requires_grad_()
    neighbors = knn(pos.detach(), 8)
    loss = arap_loss(pos, pos + 1, neighbors, torch.ones(1, 0, dtype=torch.float64))
    loss.backward()
    assert loss.item() == 0.0

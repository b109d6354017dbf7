"""Cropping a HexPlane to the Gaussians that query it (issue 6: model only what a scene
needs). The cropped field must give the same features wherever those Gaussians sit,
survive checkpoints, and carry Adam's moments along."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from dyngs.fields import HexPlaneConfig, HexPlaneField
from dyngs.fields.hexplane import _cut_away
from dyngs.types import SceneBox
from tests.fields.test_hexplane import _perturb_time_planes

BOX = SceneBox((-1.0, -2.0, 0.5), (2.0, 1.0, 4.5))
CONFIG = HexPlaneConfig(resolution=(9, 11, 13, 5), multires=(1, 2), features=4)


def _field(dtype: torch.dtype = torch.float32, seed: int = 0) -> HexPlaneField:
    g = torch.Generator().manual_seed(seed)
    field = CONFIG.build(BOX, generator=g).to(dtype)
    _perturb_time_planes(field, g)
    return field


def _cluster(n: int, lo: list[float], hi: list[float], dtype: torch.dtype, seed: int) -> Tensor:
    g = torch.Generator().manual_seed(seed)
    low, high = torch.tensor(lo, dtype=dtype), torch.tensor(hi, dtype=dtype)
    return low + torch.rand(n, 3, generator=g, dtype=dtype) * (high - low)


def _size(field: HexPlaneField) -> int:
    return sum(p.numel() for p in field.parameters())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_crop_keeps_the_features_where_the_points_are(dtype: torch.dtype) -> None:
    field = _field(dtype)
    # A cluster in one corner of the box, plus one point beyond its upper x face.
    xyz = torch.cat((_cluster(200, [0.1, -1.7, 1.0], [0.9, -0.6, 2.2], dtype, 1),
                     torch.tensor([[2.6, -1.0, 1.5]], dtype=dtype)))  # fmt: skip
    times = torch.rand(len(xyz), 1, generator=torch.Generator().manual_seed(2), dtype=dtype)
    before, size_before = field(xyz, times), _size(field)

    assert field.crop_to(xyz) is not None
    after = field(xyz, times)
    tolerance = 1e-12 if dtype == torch.float64 else 2e-6
    assert torch.allclose(after, before, rtol=tolerance, atol=tolerance)
    assert _size(field) < 0.6 * size_before
    # x reaches past the box, so x keeps its upper face; y and z shrink at every scale.
    assert torch.all(field.extent[:, 1, 0] == 1.0)
    assert torch.all(field.extent[:, 1, 1:] < 1.0) and torch.all(field.extent[:, 0, :] > -1.0)
    # Still a trainable field: gradients reach every cropped plane.
    field(xyz, times).square().sum().backward()
    assert all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in field.parameters())


def test_points_spanning_the_box_cut_nothing() -> None:
    field = _field()
    corners = torch.tensor([BOX.lower, BOX.upper])
    size = _size(field)
    assert field.crop_to(corners) is None and field.crop_to(corners[:0]) is None
    assert _size(field) == size and bool((field.extent.abs() == 1).all())


def test_a_single_point_keeps_one_cell() -> None:
    field = _field(torch.float64)
    point = torch.tensor([[0.3, -0.5, 2.0]], dtype=torch.float64)
    t = torch.tensor([[0.4]], dtype=torch.float64)
    before = field(point, t)
    field.crop_to(point)
    assert torch.allclose(field(point, t), before, rtol=1e-12, atol=1e-12)
    spatial = field.planes().spatial
    assert all(plane.shape[-1] == 2 and plane.shape[-2] == 2 for plane in spatial)


def test_a_cropped_field_loads_into_a_fresh_one() -> None:
    field = _field()
    xyz = _cluster(100, [-0.8, -1.5, 2.5], [0.2, 0.5, 4.0], torch.float32, 3)
    field.crop_to(xyz)
    fresh = CONFIG.build(BOX)
    fresh.load_state_dict(field.state_dict())
    t = torch.full((len(xyz), 1), 0.7)
    assert torch.equal(fresh(xyz, t), field(xyz, t))
    assert [p.shape for p in fresh.parameters()] == [p.shape for p in field.parameters()]
    # A checkpoint written before fields had an extent loads as the whole box.
    old = {k: v for k, v in _field(seed=4).state_dict().items() if k != "extent"}
    full = CONFIG.build(BOX)
    full.load_state_dict(old)
    assert torch.equal(full.planes().spatial[0], old["grids.0"][0])


def test_crop_maps_grid_shaped_state_like_the_grids() -> None:
    """Adam's moments are laid out like the grids; the returned map crops them alike."""
    field = _field()
    moments = [torch.randn(p.shape, generator=torch.Generator().manual_seed(i))
               for i, p in enumerate(field.parameters())]  # fmt: skip
    old = [p.detach().clone() for p in field.parameters()]
    crop = field.crop_to(_cluster(50, [0.5, 0.0, 1.0], [1.5, 0.8, 3.0], torch.float32, 5))
    assert crop is not None
    assert [m.shape for m in crop(moments)] == [p.shape for p in field.parameters()]
    assert all(torch.equal(a, p) for a, p in zip(crop(old), field.parameters(), strict=True))


def test_a_trimmed_crop_leaves_the_outliers_to_the_border_still_in_time() -> None:
    """With `trim`, a few far points do not hold the span open: the field keeps the nodes
    the cluster reads (same features there), and a point beyond draws the kept span's
    face in space and is still in time (its time planes 1), as the untrained room it
    was cut from."""
    dtype = torch.float64
    field = _field(dtype)
    cluster = _cluster(400, [0.1, -1.7, 1.0], [0.9, -0.6, 2.2], dtype, 6)
    far = torch.tensor([[-0.9, 0.9, 4.4], [1.9, -1.9, 0.6]], dtype=dtype)
    t = torch.full((len(cluster), 1), 0.3, dtype=dtype)
    before = field(cluster, t)
    inner = (cluster >= cluster.quantile(0.01, dim=0)) & (cluster <= cluster.quantile(0.99, dim=0))

    assert field.crop_to(torch.cat((cluster, far)), trim=0.01) is not None
    kept = inner.all(dim=1)
    assert torch.allclose(field(cluster[kept], t[kept]), before[kept], rtol=1e-12, atol=1e-12)
    assert bool((field.extent[:, 0] > -1.0).all() and (field.extent[:, 1] < 1.0).all())
    # A far point draws the spatial features the nearest point of the kept span drew
    # before the cut, times time planes of 1, at every time.
    box_lower, box_size = torch.tensor(BOX.lower), torch.tensor(BOX.size)
    lower, upper = box_lower + (field.extent[-1] + 1.0) / 2.0 * box_size
    nearest = torch.minimum(torch.maximum(far, lower), upper)
    still = _field(dtype)
    with torch.no_grad():
        for plane in still.planes().temporal:
            plane.fill_(1.0)
    fine = slice(field.features, None)  # the finest scale's features
    for time in (0.0, 0.5, 1.0):
        when = torch.full((2, 1), time, dtype=dtype)
        reference = still(nearest, when)[:, fine]
        assert torch.allclose(field(far, when)[:, fine], reference, rtol=1e-9, atol=1e-9)
    # The cluster's own points are not cut away: their motion is the field's.
    assert not bool(_cut_away(field.normalize(cluster[kept], t[kept]), field.extent[1]).any())

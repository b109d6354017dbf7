"""The compiled plane regularizers against the PyTorch reference: the plane TV, time
smoothness and time L1 of stacked plane groups, values and gradients, on planes too
short for some differences, on time planes at exactly 1 (where |1 − p| has no slope),
in float32 and float64, at any thread count; through a HexPlane field's own groups in a
step's `plane_terms`; and on a field cut to what queries it, whose terms are counted on
the whole planes."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from dyngs.config import LossConfig
from dyngs.engine.objective import plane_terms
from dyngs.fields import HexPlaneConfig, HexPlaneField
from dyngs.fields.base import PlaneGrids
from dyngs.fields.hexplane import PLANE_AXES
from dyngs.losses.compiled_planes import plane_values, usable
from dyngs.losses.temporal import time_l1_to_static, time_smoothness
from dyngs.losses.tv import plane_tv
from dyngs.types import SceneBox

pytest.importorskip("numba")

# (planes, channels, R1, R0) of each group; R1 = 1 has no step down, T = 2 no second
# difference in time, T = 3 exactly one.
SPATIAL = [(3, 4, 9, 7), (2, 4, 1, 6), (1, 4, 5, 5)]
TEMPORAL = [(2, 4, 6, 7), (1, 4, 2, 5), (1, 4, 3, 8)]


def _groups(
    shapes: list[tuple[int, int, int, int]], dtype: torch.dtype, seed: int, around: float
) -> list:
    gen = torch.Generator().manual_seed(seed)
    groups = [(around + torch.randn(s, generator=gen, dtype=torch.float64)).to(dtype)
              for s in shapes]  # fmt: skip
    if around == 1.0:  # some cells exactly 1, as the time planes start
        groups[0][0, 0, :2] = 1.0
    return [g.requires_grad_(True) for g in groups]


def _reference(spatial: list, temporal: list) -> torch.Tensor:
    views = [plane for g in spatial for plane in g.unbind(0)]
    times = [plane for g in temporal for plane in g.unbind(0)]
    return torch.stack((plane_tv(views), time_smoothness(times), time_l1_to_static(times)))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_values_and_gradients_are_the_references(dtype: torch.dtype) -> None:
    tolerance = {torch.float32: 1e-5, torch.float64: 1e-12}[dtype]
    spatial, temporal = _groups(SPATIAL, dtype, 0, 0.0), _groups(TEMPORAL, dtype, 1, 1.0)
    assert usable(spatial + temporal)
    upstream = torch.tensor([0.7, -1.3, 2.1], dtype=dtype)
    got = plane_values(spatial, temporal)
    (got * upstream).sum().backward()
    got_grads = [g.grad.clone() for g in spatial + temporal]
    for g in spatial + temporal:
        g.grad = None
    want = _reference(spatial, temporal)
    (want * upstream).sum().backward()
    torch.testing.assert_close(got, want.detach(), rtol=tolerance, atol=0)
    for mine, theirs in zip(got_grads, (g.grad for g in spatial + temporal), strict=True):
        assert theirs is not None
        assert float((mine - theirs).abs().max()) <= tolerance * float(theirs.abs().max())
    # Where a time plane is exactly 1, the L1 pull has no slope, as PyTorch's `abs`.
    assert float(got_grads[3][0, 0, :2].abs().max()) < 1.0  # only the smoothness part


def test_an_empty_kind_is_zero_and_the_other_is_unchanged() -> None:
    spatial = _groups(SPATIAL, torch.float64, 0, 0.0)
    alone = plane_values(spatial, [])
    assert alone[1:].tolist() == [0.0, 0.0]
    torch.testing.assert_close(alone[0], plane_tv([p for g in spatial for p in g.unbind(0)]),
                               rtol=1e-12, atol=0)  # fmt: skip


def test_the_same_at_every_thread_count() -> None:
    spatial, temporal = (
        _groups(SPATIAL, torch.float32, 2, 0.0),
        _groups(TEMPORAL, torch.float32, 3, 1.0),
    )
    before = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            for g in spatial + temporal:
                g.grad = None
            values = plane_values(spatial, temporal)
            values.sum().backward()
            results.append((values.detach(), [g.grad.clone() for g in spatial + temporal]))
    finally:
        torch.set_num_threads(before)
    assert torch.equal(results[0][0], results[1][0])
    assert all(torch.equal(a, b) for a, b in zip(results[0][1], results[1][1], strict=True))


def test_a_fields_groups_give_the_step_the_references_terms() -> None:
    box = SceneBox((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    field = HexPlaneConfig(resolution=(9, 7, 8, 5), features=4).build(
        box, generator=torch.Generator().manual_seed(0)
    )
    with torch.no_grad():
        for grid in field.grids:
            grid.add_(0.1 * torch.randn(grid.shape, generator=torch.Generator().manual_seed(1)))
    weights = LossConfig()
    grouped = field.planes()
    assert grouped.spatial_groups and grouped.temporal_groups
    views = PlaneGrids(spatial=grouped.spatial, temporal=grouped.temporal)  # no groups
    results = []
    for planes in (grouped, views):
        field.zero_grad()
        terms = plane_terms(weights, planes)
        torch.stack(list(terms.values())).sum().backward()
        results.append((terms, [g.grad.clone() for g in field.grids]))
    (compiled, compiled_grads), (reference, reference_grads) = results
    assert compiled.keys() == reference.keys() == {"plane_tv", "time_smoothness", "time_l1"}
    for name in compiled:
        torch.testing.assert_close(compiled[name], reference[name], rtol=1e-5, atol=0)
    for mine, theirs in zip(compiled_grads, reference_grads, strict=True):
        assert float((mine - theirs).abs().max()) <= 1e-5 * float(theirs.abs().max())


def _plane_grads(field: HexPlaneField, planes: PlaneGrids) -> list[list[torch.Tensor]]:
    """The regularizers' gradient on each plane, per scale in PLANE_AXES order."""
    field.zero_grad()
    terms = plane_terms(LossConfig(), planes)
    torch.stack(list(terms.values())).sum().backward()
    return [[field.grids[i].grad[slot].clone() for i, slot in where] for where in field._where]


@pytest.mark.parametrize("compiled", [True, False])
def test_a_cut_field_regularizes_each_kept_cell_as_the_whole_one_did(compiled: bool) -> None:
    """The regularizers count a cut plane's terms on its whole size: each cell the cut
    keeps, away from the cut's edge, gets the gradient it got in the whole field (its
    share of every mean unchanged), on the compiled path and the reference alike."""
    box = SceneBox((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    gen = torch.Generator().manual_seed(0)
    field = HexPlaneConfig(resolution=(17, 15, 16, 6), features=4).build(box, generator=gen)
    with torch.no_grad():
        for grid in field.grids:
            grid.add_(0.1 * torch.randn(grid.shape, generator=gen, dtype=grid.dtype))
    whole_grads = _plane_grads(field, field.planes())
    corner = torch.tensor([[-0.2, -0.5, 0.1], [0.6, 0.3, 0.7]])
    assert field.crop_to(corner) is not None
    cut = field.planes()
    if not compiled:
        cut = dataclasses.replace(cut, spatial_groups=[], temporal_groups=[])
    cut_grads = _plane_grads(field, cut)
    for s, first in enumerate(_first_kept_nodes(field)):
        for plane, (a, b) in enumerate(PLANE_AXES):
            spatial = plane < 3
            mine, theirs = cut_grads[s][plane], whole_grads[s][plane]
            rows, columns = mine.shape[-2:]
            rows_at = slice(first[b], first[b] + rows) if spatial else slice(None)
            theirs = theirs[:, rows_at, first[a] : first[a] + columns]
            if spatial:  # a cell at the cut's edge lost the steps to its dropped neighbours
                mine, theirs = mine[:, 1:-1, 1:-1], theirs[:, 1:-1, 1:-1]
            assert mine.numel() > 0
            torch.testing.assert_close(mine, theirs, rtol=1e-5, atol=1e-12)


def _first_kept_nodes(field: HexPlaneField) -> list[list[int]]:
    """Per scale, the whole grid's index of the first node the cut kept along x, y, z."""
    firsts = []
    for s, sizes in enumerate(field._whole):
        counts = torch.tensor([sizes[0][1], sizes[0][0], sizes[1][0]], dtype=torch.float64)
        first = (field.extent[s, 0].double() + 1.0) / 2.0 * (counts - 1)
        firsts.append(first.round().long().tolist())
    return firsts

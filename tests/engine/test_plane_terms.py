"""The plane regularizers of a step: which run by default, and each weight switching its
own term on and off."""

from __future__ import annotations

import pytest
import torch

from dyngs.config import LossConfig
from dyngs.engine.objective import plane_terms
from dyngs.fields.base import PlaneGrids
from dyngs.losses.tv import plane_roughness, plane_tv


def _planes() -> PlaneGrids:
    gen = torch.Generator().manual_seed(0)
    spatial = [torch.rand(4, 6, 5, generator=gen) for _ in range(3)]
    temporal = [1 + 0.1 * torch.rand(4, 7, 5, generator=gen) for _ in range(3)]
    return PlaneGrids(spatial=spatial, temporal=temporal)


def test_the_default_is_the_tv_alone() -> None:
    planes = _planes()
    defaults = LossConfig()
    terms = plane_terms(defaults, planes)
    assert "plane_roughness" not in terms
    assert torch.equal(terms["plane_tv"], defaults.plane_tv * plane_tv(planes.spatial))


@pytest.mark.parametrize("tv, roughness", [(0.0, 0.0), (2e-3, 0.0), (0.0, 5e-3), (2e-3, 5e-3)])
def test_each_weight_switches_its_own_term(tv: float, roughness: float) -> None:
    planes = _planes()
    terms = plane_terms(LossConfig(plane_tv=tv, plane_roughness=roughness), planes)
    assert ("plane_tv" in terms) == (tv > 0)
    assert ("plane_roughness" in terms) == (roughness > 0)
    if tv > 0:
        assert torch.equal(terms["plane_tv"], tv * plane_tv(planes.spatial))
    if roughness > 0:
        assert torch.equal(terms["plane_roughness"], roughness * plane_roughness(planes.spatial))


def test_a_field_without_planes_costs_nothing() -> None:
    assert plane_terms(LossConfig(plane_tv=1.0, plane_roughness=1.0), PlaneGrids()) == {}
